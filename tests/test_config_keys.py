"""Every configuration key is declared once (issue 32, ADR 0021): a device's in
``drivers.registry``, the ``[cage]`` and ``[lab]`` tables' in ``rig.config``. The loader fills in
the declared defaults and refuses any other key with the file, the line and the nearest valid
key; ``docs/devices.md`` shows the same declarations; every configuration the project ships or
writes loads under that rule."""

from __future__ import annotations

import datetime as dt
import re
import tomllib
from pathlib import Path
from typing import Any

import pytest

from bench.labfixture import RIG_TOML as LAB_FIXTURE_TOML
from drivers.registry import KINDS, RECORD_KEYS, OpenSpec
from rig.cli import main
from rig.config import (
    CAGE_KEYS,
    DOC_FILE,
    LAB_KEYS,
    TABLES,
    _devices,
    _Source,
    _table,
    keys_doc,
    line_of,
    load_rig_config,
    with_keys_doc,
)
from rig.errors import UserInputError
from rig.sim_rig import device_lines, sim_rig_config
from sim.cage import SimulatedCage
from sim.config import load_config

ROOT = Path(__file__).resolve().parent.parent
HMR = '[devices.dut]\nkind = "hmr2300"\nprotocol = "serial"\npath = "/dev/ttyUSB1"\n'
CAGE = """
[cage]
axes = { x = "cx", y = "cx", z = "cx" }
max_current_a = [1.0, 1.0, 1.0]
max_field_ut = 100.0
max_slew_a_per_s = 1.0

[devices.cx]
kind = "riden-rd60xx"
protocol = "modbus-tcp"
host = "127.0.0.1"
port = 502
"""
REQUIRED = {"host": "127.0.0.1", "port": 502, "path": "/dev/ttyUSB0", "address": 0x20,
            "regmap": "hm310p"}  # fmt: skip
"""A valid value for each required key (to load one device of every kind and transport)."""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(text, encoding="utf-8")
    return path


def refusal(tmp_path: Path, text: str) -> str:
    with pytest.raises(UserInputError) as caught:
        load_rig_config(write(tmp_path, text))
    return str(caught.value)


# --- unknown keys: refused with the file, the line and the nearest valid key -----------------------


def test_an_unknown_device_key_names_the_file_line_key_and_nearest_valid_key(
    tmp_path: Path,
) -> None:
    text = "# a rig\n" + HMR + "device_id = 0\nstuk_after = 3\n"
    assert refusal(tmp_path, text) == (
        f"{tmp_path / 'rig.toml'}:7: [devices.dut].stuk_after: unknown key;"
        " did you mean 'stuck_after'?"
    )


def test_a_key_of_another_kind_or_transport_says_whose_it_is(tmp_path: Path) -> None:
    message = refusal(tmp_path, HMR + 'regmap = "hm310p"\n')
    assert ":5: [devices.dut].regmap: unknown key: it is a key of regmap-supply" in message
    assert "not of hmr2300 over serial (its keys: " in message and "stuck_after" in message
    message = refusal(tmp_path, HMR + "parity = 'N'\n")
    assert "it is a key of modbus-rtu devices, not of hmr2300 over serial" in message


def test_a_wrong_type_is_refused(tmp_path: Path) -> None:
    message = refusal(tmp_path, HMR + 'stuck_after = "abc"\n')
    assert message.endswith("[devices.dut].stuck_after: must be a whole number, got 'abc'")


@pytest.mark.parametrize(
    ("line", "key", "said"),
    [("correction_matrix = [[1, 2], [3]]", "correction_matrix", "3 x 3 finite numbers"),
     ("correction_matrix = [[1, 0, 0], [0, 1, 0], [0, 0, nan]]", "correction_matrix", "3 x 3"),
     ("correction_offset_ut = [0.0, 0.0]", "correction_offset_ut", "a list of 3 finite numbers"),
     ("position_m = [0, 0, true]", "position_m", "e.g. position_m = [0.0, 0.0, -0.08]")],
)  # fmt: skip
def test_a_certificate_or_place_of_the_wrong_shape_is_refused(
    tmp_path: Path, line: str, key: str, said: str
) -> None:
    """A malformed certificate or place would crash the fit or the budget mid-run: refused when
    the configuration loads, naming the key and the shape wanted."""
    message = refusal(tmp_path, HMR + line + "\n")
    assert f"[devices.dut].{key}: must be" in message and said in message, message


@pytest.mark.parametrize(
    ("text", "line", "where", "near"),
    [
        ('[devices]\ndut = { kind = "hmr2300", protocol = "serial", path = "/dev/x",'
         " stuk_after = 3 }\n", 2, "[devices.dut].stuk_after", "stuck_after"),
        ('devices.dut.kind = "hmr2300"\ndevices.dut.protocol = "serial"\n'
         'devices.dut.path = "/dev/x"\ndevices.dut.rate_hx = 20\n', 4, "[devices.dut].rate_hx",
         "rate_hz"),
        ('[devices."dut"]\nkind = "hmr2300"\nprotocol = "serial"\npath = "/dev/x"\n'
         "  baudrat = 9600   # indented\n", 5, "[devices.dut].baudrat", "baudrate"),
    ],
)  # fmt: skip
def test_the_line_is_found_in_inline_tables_dotted_keys_and_quoted_names(
    tmp_path: Path, text: str, line: int, where: str, near: str
) -> None:
    message = refusal(tmp_path, text)
    assert message.startswith(f"{tmp_path / 'rig.toml'}:{line}: {where}: unknown key")
    assert message.endswith(f"did you mean '{near}'?")


def test_without_a_line_the_error_still_names_file_and_key() -> None:
    assert line_of('[devices.dut]\nkind = "x"\n', ("devices", "dut", "kind")) == 2
    assert line_of('[devices.dut]\nkind = "x"\n', ("devices", "other", "kind")) is None
    assert line_of("[devices.dut.inner]\nkey = 1\n", ("devices", "dut")) == 1  # inside it


def test_cage_unknown_key_and_defaults(tmp_path: Path) -> None:
    message = refusal(tmp_path, CAGE.replace("max_field_ut", "max_feild_ut"))
    assert ":5: [cage].max_feild_ut: unknown key; did you mean 'max_field_ut'?" in message
    cage = load_rig_config(write(tmp_path, CAGE)).cage
    assert cage is not None
    declared = {p.name: p.default for p in CAGE_KEYS}
    assert (cage.compliance_v, cage.step_s) == (declared["compliance_v"], declared["step_s"])
    message = refusal(tmp_path, CAGE.replace("max_field_ut = 100.0", "max_field_ut = -1"))
    assert message.endswith("[cage].max_field_ut: must be more than 0, got -1; write the cage's"
                            " field limit, e.g. max_field_ut = 150.0")  # fmt: skip
    assert refusal(tmp_path, CAGE.replace("max_slew_a_per_s = 1.0", "")).endswith(
        "[cage]: needs 'max_slew_a_per_s' (coil current slew limit)"
    )


def test_lab_unknown_key_and_unknown_tables_are_refused(tmp_path: Path) -> None:
    message = refusal(tmp_path, '[lab]\nrig = "cage-1"\nuri = "postgresql://rig@h/lab"\n')
    assert message.endswith(":3: [lab].uri: unknown key; did you mean 'url'?")
    message = refusal(tmp_path, "[cgae]\nmax_field_ut = 1\n")
    assert message.endswith(":1: [cgae]: unknown table; did you mean 'cage'?")
    message = refusal(tmp_path, "seed = 7\n")
    assert message.endswith(":1: [seed]: unknown table; the keys here: cage, devices, lab")
    assert set(TABLES) == {"devices", "cage", "lab"}


def test_rig_check_refuses_an_unknown_key_in_its_rig_configuration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, HMR + "stuk_after = 3\n")
    assert main(["-q", "check", "smoke", "--rig", str(path)]) == 2
    assert "[devices.dut].stuk_after: unknown key; did you mean 'stuck_after'?" in (
        capsys.readouterr().err
    )


# --- defaults: applied once, when the file loads --------------------------------------------------


def every_key_with_a_default() -> list[tuple[str, str, str, Any]]:
    return [(kind.name, protocol, p.name, p.default) for kind in KINDS.values()
            for protocol in kind.transports for p in kind.param_specs(protocol)
            if p.default is not None]  # fmt: skip


@pytest.mark.parametrize(("kind", "protocol", "key", "default"), every_key_with_a_default())
def test_each_declared_default_is_applied(
    tmp_path: Path, kind: str, protocol: str, key: str, default: Any
) -> None:
    required = [p.name for p in KINDS[kind].param_specs(protocol) if p.required]
    lines = [f'kind = "{kind}"', f'protocol = "{protocol}"']
    lines += [f"{k} = {REQUIRED[k]!r}".replace("'", '"') for k in required]
    cfg = load_rig_config(write(tmp_path, "[devices.d]\n" + "\n".join(lines) + "\n"))
    assert cfg.devices["d"].get(key) == default
    assert cfg.raw["devices"]["d"].get(key) is None  # the file as written is kept


def test_the_engine_reads_the_applied_stuck_after(tmp_path: Path) -> None:
    for module in (ROOT / "rig" / "engine").glob("*.py"):  # the default is declared once
        text = module.read_text(encoding="utf-8")
        assert re.search(r"STUCK_AFTER|get\(\"stuck_after\", \d", text) is None, module
    assert load_rig_config(write(tmp_path, HMR)).devices["dut"].get("stuck_after") == 60


def test_kinds_state_their_own_transport_defaults() -> None:
    assert KINDS["hmr2300"].defaults("serial")["baudrate"] == 9600
    assert KINDS["ascii-mag"].defaults("serial")["baudrate"] == 115200
    assert KINDS["riden-rd60xx"].defaults("modbus-rtu")["baudrate"] == 115200
    for name in ("regmap-supply", "regmap-eload", "regmap-relay", "regmap-thermometer"):
        assert "baudrate" not in KINDS[name].defaults("modbus-rtu")  # the map's factory rate


def test_an_opener_sees_the_defaults_however_the_spec_was_made(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    seen: dict[str, Any] = {}

    def fake_hmr2300(path: str, baudrate: int, device_id: Any, name: str) -> None:
        seen.update(path=path, baudrate=baudrate)

    monkeypatch.setattr("drivers.registry.Hmr2300", fake_hmr2300)
    KINDS["hmr2300"].open(OpenSpec("dut", "serial", {"path": "/dev/x"}))
    assert seen == {"path": "/dev/x", "baudrate": 9600}


def test_record_keys_are_accepted_by_every_kind(tmp_path: Path) -> None:
    cfg = load_rig_config(write(tmp_path, HMR + 'serial = "0123"\ncalibrated_on = 2026-01-15\n'))
    assert cfg.devices["dut"].get("calibrated_on") == dt.date(2026, 1, 15)
    assert refusal(tmp_path, HMR + 'calibrated_on = "last week"\n').endswith(
        "[devices.dut].calibrated_on: must be a TOML date (2026-01-15, no quotes), got 'last week'"
    )
    record = {p.name for p in RECORD_KEYS}
    for kind in KINDS.values():
        assert all(record <= {p.name for p in kind.param_specs(t)} for t in kind.transports)


# --- docs/devices.md shows the declarations -------------------------------------------------------


def test_the_key_tables_in_docs_devices_md_match_the_declarations() -> None:
    text = (ROOT / DOC_FILE).read_text(encoding="utf-8")
    assert with_keys_doc(text) == text, "run: python -m rig.config --doc --write"
    for kind in KINDS.values():
        for protocol in kind.transports:
            for p in kind.param_specs(protocol):
                assert f"`{p.name}`" in keys_doc()
    for p in (*CAGE_KEYS, *LAB_KEYS):
        assert f"`{p.name}`" in keys_doc()


# --- every configuration the project ships or writes loads --------------------------------------


def doc_blocks() -> list[tuple[str, str]]:
    """Every ```toml block of the docs and the README that is a rig configuration."""
    out = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for i, block in enumerate(re.findall(r"```toml\n(.*?)```", path.read_text(), re.S)):
            if re.search(r"^\[(devices\.|cage\]|lab\])", block, re.M):
                out.append((f"{path.name}#{i}", block))
    return out


@pytest.mark.parametrize(("name", "block"), doc_blocks())
def test_every_rig_configuration_in_the_docs_uses_declared_keys(name: str, block: str) -> None:
    """A doc's fragment may name devices it does not show: its keys, types and values are checked
    (a table at a time), not the devices the ``[cage]`` names."""
    raw = tomllib.loads(block)
    src = _Source(Path(name), block)
    assert set(raw) <= set(TABLES)
    _devices(src, raw.get("devices", {}))
    for table, keys in (("cage", CAGE_KEYS), ("lab", LAB_KEYS)):
        if table in raw:
            _table(src, table, raw[table], keys)


def test_the_lab_fixture_configuration_loads(tmp_path: Path) -> None:
    text = LAB_FIXTURE_TOML.format(rig="cage-1", ref_serial=100, calibrated_on="2026-01-15",
                                   expires="2027-01-15")  # fmt: skip
    assert set(load_rig_config(write(tmp_path, text)).devices) == {"reference", "dut"}


def test_the_configuration_rig_sim_writes_loads(tmp_path: Path) -> None:
    cfg = load_config()
    with SimulatedCage(cfg) as cage:
        text = sim_rig_config(cage.endpoints_document(), cfg)
    rig = load_rig_config(write(tmp_path, text))
    assert set(rig.devices) == set(cage.endpoints)
    for written in ("role", "stopbits", "line_format", "unit"):
        assert f"\n{written} =" not in text


def test_the_sim_writer_refuses_an_endpoint_entry_it_cannot_write() -> None:
    dev = {"kind": "hmr2300", "protocol": "serial", "path": "/dev/x", "role": "dut"}
    assert device_lines("dut", dev) == ['[devices.dut]', 'kind = "hmr2300"',
                                        'protocol = "serial"', 'path = "/dev/x"', ""]  # fmt: skip
    with pytest.raises(ValueError, match=r"no rig configuration key \['colour'\]"):
        device_lines("dut", dev | {"colour": "red"})
    with pytest.raises(ValueError, match="not the drivers' defaults"):
        device_lines("dut", dev | {"unit": "nT"})


def test_rig_safe_reads_a_configuration_with_stray_keys(tmp_path: Path) -> None:
    """An emergency stop is never refused over a misspelt key: ``rig safe``'s reading passes over
    unknown keys and tables (every other command refuses them)."""
    cfg = tmp_path / "rig.toml"
    cfg.write_text('[devices.coil_x]\nkind = "riden-rd60xx"\nprotocol = "modbus-tcp"\n'
                   'host = "127.0.0.1"\nport = 5020\nstuk_after = 3\n[extra]\nx = 1\n')  # fmt: skip
    with pytest.raises(UserInputError, match="unknown"):
        load_rig_config(cfg)
    loaded = load_rig_config(cfg, check_text=False)
    assert "stuk_after" not in loaded.devices["coil_x"].params
    assert loaded.devices["coil_x"].get("port") == 5020
