"""The register-map format's coils, model codes, constant-current selection and switched relays
(docs/adr/0040): each new key is checked at load, one line naming the file, the line and the
fix, and the rules that keep a load out of CV hold for every map."""

from __future__ import annotations

from pathlib import Path

import pytest

from regmaps import RegisterMapError, load_map, parse_map, shipped_maps

LOAD = """[device]
kind = "eload"
v_max = 150.0
i_max = 30.0

[[registers]]
name = "cmd"
address = 0x0A00
type = "uint16"
access = "rw"
role = "output"
on = 42
off = 43
cc = 1

[[registers]]
name = "i_set"
address = 0x0A01
type = "float32"
access = "rw"
role = "i_set"

[[registers]]
name = "mode"
address = 0x0B04
type = "uint16"
role = "mode"
mask = 0x00FF

[[registers]]
name = "remote"
address = 0x0A00
type = "coil"
access = "rw"
role = "remote"

[[registers]]
name = "model"
address = 0x0B06
type = "uint16"
role = "model"
models = { 101 = "M9812", 0x1C = "M9710" }
"""


def test_a_load_map_with_every_new_key_loads() -> None:
    m = parse_map(LOAD, "load.toml")
    assert m.cc_select() == (m.require("output"), 1.0)
    assert m.require("remote").is_coil  # coil 0x0A00 beside register 0x0A00: separate spaces
    mode = m.require("mode")
    assert mode.reads_cc(0xFF01) and not mode.reads_cc(0xFF02) and not mode.reads_cc(0x0002)
    assert m.require("model").models == ((101, "M9812"), (28, "M9710"))
    found = m.identify(lambda reg: 28.0)
    assert (found.model, found.code, found.warning, found.mismatch) == ("M9710", 28, "", "")
    refused = m.identify(lambda reg: 53.0)  # unknown = "refuse", the default
    assert refused.mismatch.startswith("model register 'model' (0x0b06) reads 53, not one of")
    # no cc command, a writable mode register: CC is selected by writing its cc there
    text = LOAD.replace("cc = 1\n", "").replace(
        "mask = 0x00FF\n", 'mask = 0x00FF\ncc = 3\naccess = "rw"\n'
    )
    writable = parse_map(text, "load.toml")
    assert writable.cc_select() == (writable.require("mode"), 3.0)


@pytest.mark.parametrize(("old", "new", "bad", "expect"), [
    ("cc = 1\n", "", 'kind = "eload"', "an electronic load map must say how constant current is selected"),
    ('role = "mode"\nmask = 0x00FF\n', 'role = "none"\n', 'kind = "eload"', "the output's cc command needs a register of role 'mode'"),
    ("off = 43\ncc = 1", "cc = 1", "cc = 1", "cc on an output is the command that selects constant current"),
    ('role = "i_set"', 'role = "i_set"\ncc = 2', "cc = 2", "cc belongs to a register with role 'output' or 'mode'"),
    ("mask = 0x00FF", "mask = 0", "mask = 0", "register 'mode': mask 0 must be a whole number of 1 to 0xFFFF"),
    ('type = "float32"\naccess = "rw"\nrole = "i_set"', 'type = "float32"\naccess = "rw"\nrole = "i_set"\nmask = 1', "mask = 1", "mask belongs to a register with role 'mode'"),
    ('type = "coil"', 'type = "coil"\nscale = 10', "scale = 10", "register 'remote' is a coil (one bit): remove its scale"),
    ('role = "remote"', 'role = "remote"\nvalue = 2', "value = 2", "register 'remote': value 2 does not fit a coil"),
    ('0x1C = "M9710"', '"M97" = "M9710"', '"M97"', "register 'model': model code 'M97' must be a whole number of 0 to 65535"),
    ('models = { 101 = "M9812", 0x1C = "M9710" }', "models = {}", "models = {}", "models must be a table of 1 to 256 code = \"model\""),
    ('models = { 101 = "M9812", 0x1C = "M9710" }\n', "", 'role = "model"', "a model register lists its codes: models = "),
    ('role = "model"', 'role = "model"\nunknown = "guess"', "unknown", "unknown unknown 'guess'"),
    ('role = "model"', 'role = "none"\nunknown = "warn"', "models =", "models belongs to a register with role 'model'"),
    ('address = 0x0A00\ntype = "coil"', 'address = 0x0A01\ntype = "coil"\naccess = "rw"\n[[registers]]\nname = "c2"\naddress = 0x0A01\ntype = "coil"', None, "registers 'c2' and 'remote' overlap at 0x0a01"),
])  # fmt: skip
def test_each_new_key_is_checked_in_one_line(
    tmp_path: Path, old: str, new: str, bad: str | None, expect: str
) -> None:
    assert old in LOAD
    path = tmp_path / "load.toml"
    path.write_text(LOAD.replace(old, new, 1), encoding="utf-8")
    with pytest.raises(RegisterMapError) as info:
        load_map(str(path))
    message = str(info.value)
    assert "\n" not in message and expect in message, message
    if bad is not None:
        line = next(i for i, ln in enumerate(path.read_text().splitlines(), 1) if bad in ln)
        assert message.startswith(f"{path}:{line}: "), message


def test_every_shipped_load_selects_cc_and_every_relay_switches_one_way() -> None:
    """No shipped load can be switched on without selecting constant current; every relay
    board's relays are switched registers or coils (the driver reads each switch back)."""
    loads = [m for m in shipped_maps() if m.kind == "eload"]
    assert loads and all(m.cc_select() is not None and m.role("mode") for m in loads)
    relays = {m.name: m for m in shipped_maps() if m.kind == "relay"}
    assert {"waveshare-relay", "r421a08-relay", "relay-h-bridge"} <= set(relays)
    for m in relays.values():
        regs = [m.require(f"polarity_{ax}") for ax in "xyz"]
        assert all(r.access == "rw" and r.on != r.off for r in regs), m.name
    assert all(r.is_coil for r in relays["waveshare-relay"].registers)
    commands = relays["r421a08-relay"].registers
    assert [(r.address, r.on, r.off) for r in commands] == [(n, 0x0100, 0x0200) for n in (1, 2, 3)]
