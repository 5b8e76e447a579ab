"""The device registry is the one list of kinds: configuration checking, the guardian's outputs and
the roles the cage accepts all come from it."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.registry import (
    KINDS,
    TRANSPORTS,
    all_params,
    kinds_with_role,
    output_kinds,
    output_range,
)
from regmaps import shipped_maps
from rig.config import DEVICE_KINDS, load_rig_config
from rig.engine.guardian import OUTPUT_KINDS
from rig.errors import UserInputError


def test_every_kind_is_complete() -> None:
    for name, kind in KINDS.items():
        assert kind.name == name and kind.roles and kind.description
        assert set(kind.transports) <= set(TRANSPORTS)
        assert kind.probe is not None, f"{name} cannot be found by rig devices scan"
    assert {name: k.transports for name, k in KINDS.items()} == DEVICE_KINDS


def test_outputs_and_roles_come_from_the_registry() -> None:
    assert set(OUTPUT_KINDS) == set(output_kinds())
    assert set(OUTPUT_KINDS) == {"riden-rd60xx", "regmap-supply", "regmap-eload", "regmap-relay"}
    # the shipped ones at least (a new magnetometer kind needs no edit here)
    assert set(kinds_with_role("magnetometer")) >= {"hmr2300", "ascii-mag", "rm3100", "lis3mdl"}
    assert set(kinds_with_role("load")) >= {"riden-rd60xx", "regmap-eload"}


def test_every_supply_and_load_kind_tells_its_range_before_it_is_opened() -> None:
    """``rig check``'s heat limits bound a heater by its output's range (docs/devices.md, "How to
    add any other device", step 2)."""
    currents = set(kinds_with_role("supply")) | set(kinds_with_role("load"))
    assert currents and not [k for k in currents if KINDS[k].range_of is None]
    assert output_range("riden-rd60xx", {}) is not None
    mapped = output_range("regmap-supply", {"regmap": "dps5005"})
    assert mapped is not None and mapped.max_current_a == 5.0 and mapped.sets_voltage
    assert output_range("regmap-relay", {"regmap": "waveshare-relay"}) is None
    assert output_range("regmap-supply", {"regmap": "no-such-map"}) is None


DEVICES_MD = Path(__file__).resolve().parents[2] / "docs" / "devices.md"


def section(title: str) -> str:
    text = DEVICES_MD.read_text(encoding="utf-8")
    return text.split(f"\n{title}\n", 1)[1].split("\n#", 1)[0]


def test_every_kind_and_shipped_map_has_its_docs_row() -> None:
    kinds = section("## The device kinds")
    missing = [k for k in KINDS if f"| `{k}` |" not in kinds]
    assert not missing, f"docs/devices.md 'The device kinds' has no row for {missing}"
    maps = section("### Register-map instruments (`regmaps/*.toml`, one parser: ADR 0019)")
    listed = {name for line in maps.splitlines() if line.startswith("| `")
              for name in line.split("|")[1].replace("`", "").replace(" ", "").split(",")}  # fmt: skip
    missing = [m.name for m in shipped_maps() if m.name not in listed]
    assert not missing, f"docs/devices.md 'Register-map instruments' has no row for {missing}"


def test_a_parameter_name_has_one_type_everywhere() -> None:
    params = all_params()
    for kind in KINDS.values():
        for protocol in kind.transports:
            for p in kind.param_specs(protocol):
                assert params[p.name].types == p.types, p.name


def test_shipped_register_maps_load() -> None:
    maps = {m.name: m for m in shipped_maps()}
    assert {"maynuo-m97", "bipolar-supply", "relay-h-bridge"} <= set(maps)
    model = maps["maynuo-m97"].require("model")
    assert model.models == ((101, "Maynuo M9812"), (28, "Maynuo M9710"))


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "rig.toml"
    p.write_text(text, encoding="utf-8")
    return p


@pytest.mark.parametrize(
    ("device", "message"),
    [
        ('kind = "riden"\nprotocol = "modbus-tcp"', r"\[devices.d\].kind: 'riden' is not one of riden-rd60xx"),
        ('kind = "hmr2300"\nprotocol = "modbus-tcp"', r"'modbus-tcp' does not suit hmr2300; use serial"),
        ('kind = "regmap-eload"\nprotocol = "modbus-rtu"\npath = "/dev/ttyUSB0"',
         r"\[devices.d\]: needs 'regmap' \(a register-map file or a shipped map name"),
        ('kind = "rm3100"\nprotocol = "i2c"', r"needs 'address' for i2c"),
        ('kind = "riden-rd60xx"\nprotocol = "modbus-tcp"\nhost = "h"\nport = "502"',
         r"\[devices.d\].port: must be a whole number, got '502'"),
        ('kind = "ascii-mag"\nprotocol = "serial"\npath = "/dev/x"\nrate_hz = "fast"',
         r"\[devices.d\].rate_hz: must be a number"),
    ],
)  # fmt: skip
def test_configuration_errors_name_the_file_key_and_fix(
    tmp_path: Path, device: str, message: str
) -> None:
    with pytest.raises(UserInputError, match=r"rig.toml: .*" + message):
        load_rig_config(write(tmp_path, f"[devices.d]\n{device}\n"))


def test_cage_roles_come_from_the_registry(tmp_path: Path) -> None:
    text = """
[cage]
axes = { x = "mag", y = "mag", z = "mag" }
max_current_a = [1, 1, 1]
max_field_ut = 100.0
max_slew_a_per_s = 1.0
[devices.mag]
kind = "hmr2300"
protocol = "serial"
path = "/dev/ttyUSB0"
"""
    with pytest.raises(
        UserInputError, match=r"\[cage\].axes.x: 'mag' is not a supply .*riden-rd60xx"
    ):
        load_rig_config(write(tmp_path, text))


def test_unknown_keys_are_refused(tmp_path: Path) -> None:
    """Issue 32: a key no kind declares is refused (it used to pass through unread)."""
    with pytest.raises(
        UserInputError, match=r"rig.toml:6: \[devices.ref\].line_format: unknown key"
    ):
        load_rig_config(write(tmp_path, """
[devices.ref]
kind = "ascii-mag"
protocol = "serial"
path = "/dev/ttyUSB0"
line_format = "{x} {y} {z}"
"""))  # fmt: skip
