"""The one register-map parser (regmaps/, ADR 0019): every key, role, kind, type and access is
checked, and a mistake is refused at load with the file, the line and the nearest valid name."""

from __future__ import annotations

from pathlib import Path

import pytest

import drivers.regmap
import sim.regmap
from regmaps import MAP_DIR, RegisterMapError, load_map, shipped_maps
from sim.config import SimConfigError

HM310P = (MAP_DIR / "hm310p.toml").read_text(encoding="utf-8")


def broken(tmp_path: Path, old: str, new: str, count: int = 1) -> Path:
    assert old in HM310P
    path = tmp_path / "hm310p-typo.toml"
    path.write_text(HM310P.replace(old, new, count), encoding="utf-8")
    return path


def line_of(path: Path, text: str) -> int:
    return next(i for i, ln in enumerate(path.read_text().splitlines(), 1) if text in ln)


def test_a_misspelled_role_is_refused_with_file_line_and_fix(tmp_path: Path) -> None:
    path = broken(tmp_path, 'role = "protection"', 'role = "protecton"')
    with pytest.raises(RegisterMapError) as info:
        load_map(str(path))
    message = str(info.value)
    assert message.startswith(f"{path}:{line_of(path, 'protecton')}: unknown role 'protecton';")
    assert "did you mean 'protection'?" in message and "\n" not in message


def test_the_simulator_refuses_it_too(tmp_path: Path) -> None:
    path = broken(tmp_path, 'role = "protection"', 'role = "protecton"')
    with pytest.raises(
        SimConfigError, match=r"unknown role 'protecton'; did you mean 'protection'"
    ):
        sim.regmap.load_regmap(str(path))


@pytest.mark.parametrize(("old", "new", "bad", "fix"), [
    ("scale = 100\n", "scael = 100\n", "scael", "unknown key 'scael'; did you mean 'scale'?"),
    ('access = "rw"', 'acess = "rw"', "acess", "unknown key 'acess'; did you mean 'access'?"),
    ('type = "uint16"', 'type = "unit16"', "unit16", "unknown type 'unit16'; did you mean 'uint16'?"),
    ('access = "ro"', 'access = "r-o"', 'access = "r-o"', "unknown access 'r-o'; did you mean 'ro'?"),
    ("[device]", "[device]\nvoltage = 3", "voltage", "unknown key 'voltage'; did you mean"),
    ("[device]", "[devices]", "[devices]", "unknown key 'devices'; did you mean 'device'?"),
    ("baudrate = 9600", "baudrat = 9600", "baudrat", "unknown key 'baudrat'; did you mean 'baudrate'?"),
    ('kind = "supply"', 'kind = "suply"', "suply", "unknown kind 'suply'; did you mean 'supply'?"),
])  # fmt: skip
def test_unknown_keys_and_values_name_line_and_fix(
    tmp_path: Path, old: str, new: str, bad: str, fix: str
) -> None:
    path = broken(tmp_path, old, new)
    with pytest.raises(RegisterMapError) as info:
        load_map(str(path))
    assert str(info.value).startswith(f"{path}:{line_of(path, bad)}: {fix}"), str(info.value)


def test_overlapping_registers_are_refused(tmp_path: Path) -> None:
    path = broken(tmp_path, "address = 0x0014", "address = 0x0013")
    with pytest.raises(RegisterMapError, match=r"'power' and 'powercal' overlap at 0x0013"):
        load_map(str(path))


def test_drivers_and_simulator_read_one_folder_through_one_parser() -> None:
    assert drivers.regmap.load_map is load_map
    for m in shipped_maps():
        assert sim.regmap.load_regmap(m.name) is load_map(m.name)
        assert Path(m.source).parent == MAP_DIR
    assert not (Path(drivers.regmap.__file__).parent / "regmaps").exists()
    assert not (Path(sim.regmap.__file__).parent / "regmaps").exists()


def test_protection_codes_and_flags() -> None:
    hm = load_map("hm310p").require("protection")
    assert [hm.protection_name(v) for v in (0, 1, 2, 3, 4, 8, 16)] == [
        "", "OVP", "OCP", "OVP+OCP", "OPP", "OTP", "SCP"]  # fmt: skip
    assert hm.protection_value("OCP") == 2
    dps = load_map("dps5005").require("protection")
    assert [dps.protection_name(v) for v in (0, 1, 2, 3, 9)] == ["", "OVP", "OCP", "OPP", "code 9"]


def test_command_values_belong_to_an_output_and_write_function_is_6_or_16(tmp_path: Path) -> None:
    path = broken(tmp_path, 'role = "v_set"', 'role = "v_set"\non = 42')
    with pytest.raises(
        RegisterMapError, match=r"on and off belong to a register with role 'output'"
    ):
        load_map(str(path))
    path = broken(tmp_path, "baudrate = 9600", "baudrate = 9600\nwrite_function = 7")
    with pytest.raises(RegisterMapError, match=rf"{path}:\d+: write_function must be 6 or 16"):
        load_map(str(path))
    maynuo = load_map("maynuo-m97")
    assert maynuo.write_function == 16
    assert (maynuo.require("output").on, maynuo.require("output").off) == (42.0, 43.0)
