"""The one register-map parser (regmaps/, ADR 0019): every key, role, kind, type and access is
checked, and a mistake is refused at load with the file, the line and the nearest valid name."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

import drivers
import regmaps
import sim.regmap
from regmaps import MAP_DIR, RegisterMapError, load_map, shipped_maps
from rig.procedure_files import PROCEDURES_DIR
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
    for m in shipped_maps():
        assert sim.regmap.load_regmap(m.name) is load_map(m.name)
        assert Path(m.source).parent == MAP_DIR
    # one name for the maps: the drivers have no alias of the package (issue 57)
    assert not (Path(drivers.__file__).parent / "regmap.py").exists()
    assert not (Path(drivers.__file__).parent / "regmaps").exists()
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
        RegisterMapError, match=r"on belongs to a register with role 'output', 'remote', "
    ):
        load_map(str(path))
    path = broken(tmp_path, "baudrate = 9600", "baudrate = 9600\nwrite_function = 7")
    with pytest.raises(RegisterMapError, match=rf"{path}:\d+: write_function must be 6 or 16"):
        load_map(str(path))
    maynuo = load_map("maynuo-m97")
    assert maynuo.write_function == 16
    assert (maynuo.require("output").on, maynuo.require("output").off) == (42.0, 43.0)


# --- hostile maps (issue 51): every value a map can shape is bounded, in one line -----------------


@pytest.mark.parametrize(("old", "new", "bad", "expect"), [
    ("scale = 100\n", "scale = 0\n", "scale = 0", "register 'v_out': scale is 0; it must be a finite number above 0"),
    ("scale = 100\n", "scale = nan\n", "scale = nan", "register 'v_out': scale is nan; it must be a finite"),
    ("scale = 100\n", "scale = -1\n", "scale = -1", "register 'v_out': scale is -1; it must be a finite number above 0"),
    ("scale = 100\n", "scale = inf\n", "scale = inf", "register 'v_out': scale is inf"),
    ("scale = 100\n", "scale = 1" + "0" * 400 + "\n", "scale = 1000", "register 'v_out': scale is 1000000000000000000000000000000000000...; it must"),
    ("scale = 100\n", "scale = 1e12\n", "scale = 1e12", "register 'v_out': scale is 1000000000000.0; it must be at most 1e+09"),
    ('scale = 100\n', 'scale = "100"\n', 'scale = "100"', "register 'v_out': scale is '100'"),
    ("i_max = 10.0", "i_max = inf", "i_max = inf", "i_max is inf; it must be a finite number above 0"),
    ("i_max = 10.0", "i_max = 0", "i_max = 0", "i_max is 0; it must be a finite number above 0"),
    ("v_max = 30.0", "v_max = nan", "v_max = nan", "v_max is nan"),
    ("v_max = 30.0\n", "", "[device]", "a supply map needs v_max"),
    ("address = 0x0010", "address = -1", "address = -1", "register 'v_out': address -1 is outside the Modbus address space (0 to 0xffff"),
    ("address = 0x0010", "address = 70000", "address = 70000", "register 'v_out': address 70000 is outside"),
    ("address = 0x0010", "address = 1099511627776", "address = 1099511627776", "address 1099511627776 is outside"),
    ("address = 0x0010", "address = 16.5", "address = 16.5", "address 16.5 is outside"),
    ("address = 0x0010", "address = true", "address = true", "address True is outside"),
    ("value = 3010", "value = nan", "value = nan", "register 'model': value is nan; it must be a finite number"),
    ("value = 3010", "value = 70000", "value = 70000", "register 'model': value 70000 does not fit a uint16 of scale 1 (0 to 65535)"),
    ('name = "v_out"', 'name = "v_\\u202eout"', "v_\\u202eout", "the register name 'v_\\u202eout' must be printable text"),
    ('name = "v_out"', 'name = ""', 'name = ""', "the register name '' must be printable text"),
    ('name = "output"', "name = 5", "name = 5", "the register name '5' must be printable text"),
    ('model = "Hanmatek HM310P"', 'model = "HM\\u0000"', "model = ", "the model 'HM\\x00' must be printable text"),
    ("flags = [", 'flags = ["F", "G", "H", "I", "J", "K", "L", "M", "N", "O", "P", "Q", "R", "S", "T", "U", ', "flags = [", "register 'protection' has more flags than it can report"),
    ("baudrate = 9600", "baudrate = 0", "baudrate = 0", "baudrate must be a whole number of 50 to 4000000"),
    ("baudrate = 9600", 'baudrate = 9600\nbipolar = "false"', "bipolar", "bipolar must be true or false"),
])  # fmt: skip
def test_hostile_values_are_refused_with_file_line_register_and_fix(
    tmp_path: Path, old: str, new: str, bad: str, expect: str
) -> None:
    """Each of these passed the parser (and ``rig check``) before issue 51, or was an internal
    error; now one line that starts with the file and the line of the bad value."""
    path = broken(tmp_path, old, new)
    with pytest.raises(RegisterMapError) as info:
        load_map(str(path))
    message = str(info.value)
    assert "\n" not in message and expect in message, message
    assert message.startswith(f"{path}:{line_of(path, bad.splitlines()[0])}: "), message


def test_a_name_or_role_given_twice_and_a_32_bit_register_at_the_last_address_are_refused(
    tmp_path: Path,
) -> None:
    path = broken(tmp_path, 'name = "v_out"', 'name = "i_out"')
    second = [i for i, ln in enumerate(path.read_text().splitlines(), 1) if ln == 'name = "i_out"']
    with pytest.raises(RegisterMapError, match=rf"{path}:{second[1]}: a second register named"
                       r" 'i_out' \(the first is registers\[5\]\); rename one"):  # fmt: skip
        load_map(str(path))
    path = broken(tmp_path, 'role = "v_out"', 'role = "i_out"')
    with pytest.raises(RegisterMapError, match=r"register 'i_out' has the role 'i_out' of register"
                       r" 'v_out' already; give one of them role 'none'"):  # fmt: skip
        load_map(str(path))
    path = broken(
        tmp_path, 'address = 0x0010\ntype = "uint16"', 'address = 0xffff\ntype = "uint32"'
    )
    with pytest.raises(
        RegisterMapError, match=r"address 65535 is outside .* \(0 to 0xfffe for a uint32\)"
    ):
        load_map(str(path))


@pytest.mark.parametrize(("text", "expect"), [
    ("device = 5\n", "'device' must be a table"),
    ('registers = 5\n[device]\nkind = "relay"\n', "'registers' must be tables"),
    ('registers = [1]\n[device]\nkind = "relay"\n', r"registers\[0\] must be a table"),
])  # fmt: skip
def test_tables_of_the_wrong_shape_are_refused(tmp_path: Path, text: str, expect: str) -> None:
    path = tmp_path / "shape.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(RegisterMapError, match=expect):
        load_map(str(path))


def relay_map(n: int) -> str:
    regs = "".join(
        f'[[registers]]\nname = "r{i}"\naddress = {i}\ntype = "uint16"\n' for i in range(n)
    )
    return f'[device]\nkind = "relay"\n\n{regs}'


def test_a_map_of_more_than_max_registers_is_refused_and_one_at_the_cap_is_read(
    tmp_path: Path,
) -> None:
    """30000 registers kept ``rig safe`` busy > 300 s (a quadratic parse); the parse is linear now
    (bench/bench_regmap_parse.py prints its time against tomllib's) and a map beyond the cap is
    refused before its registers are checked. Binary bytes are refused as text, not a traceback."""
    path = tmp_path / "big.toml"
    path.write_text(relay_map(regmaps.MAX_REGISTERS + 1), encoding="utf-8")
    with pytest.raises(RegisterMapError, match=rf"{path}: {regmaps.MAX_REGISTERS + 1} registers,"
                       rf" more than the {regmaps.MAX_REGISTERS} a map may have"):  # fmt: skip
        load_map(str(path))
    path.write_text(relay_map(regmaps.MAX_REGISTERS), encoding="utf-8")
    assert len(load_map(str(path)).registers) == regmaps.MAX_REGISTERS
    path.write_bytes(b'[device]\nkind = "relay"\nmodel = "\xff"\n')
    with pytest.raises(RegisterMapError, match=rf"{path}: not UTF-8 text"):
        load_map(str(path))


def test_rig_check_refuses_a_device_whose_map_is_refused(tmp_path: Path) -> None:
    """The map is read by ``rig check --rig`` (and ``rig run``'s same check), not first when the
    run opens the device: exit 2, one line naming the device, the map's line and the register."""
    path = broken(tmp_path, "scale = 100\n", "scale = 0\n")
    rig = tmp_path / "rig.toml"
    rig.write_text(f'[devices.coil_x]\nkind = "regmap-supply"\nregmap = "{path}"\n'
                   'protocol = "modbus-tcp"\nhost = "127.0.0.1"\nport = 1502\n')  # fmt: skip
    proc = PROCEDURES_DIR / "cage-characterization.yaml"
    done = subprocess.run([sys.executable, "-m", "rig.cli", "check", str(proc), "--rig", str(rig)],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert (
        f"[devices.coil_x].regmap: {path}:{line_of(path, 'scale = 0')}: register 'v_out'"
        in lines[0]
    )


def test_a_mirror_names_another_register_of_its_type_and_undefined_reads_is_closed(
    tmp_path: Path,
) -> None:
    dps = load_map("dps5005")
    assert (dps.undefined_reads, load_map("hm310p").undefined_reads) == ("exception", "zero")
    assert {r.name: r.mirror for r in dps.registers if r.mirror} == {
        "m0_v_set": "v_set", "m0_i_set": "i_set", "m0_backlight": "backlight"}  # fmt: skip
    path = broken(tmp_path, 'name = "timespan"', 'name = "timespan"\nmirror = "v_sett"')
    with pytest.raises(RegisterMapError, match=rf"{path}:{line_of(path, 'mirror =')}: register"
                       r" 'timespan': mirror 'v_sett' is not another register of this map;"
                       r" did you mean 'v_set'\?"):  # fmt: skip
        load_map(str(path))
    path = broken(tmp_path, 'name = "timespan"', 'name = "timespan"\nmirror = "ovp"')
    with pytest.raises(RegisterMapError, match=r"mirrors 'ovp' \(uint16, scale 100\) with type"
                                               r" uint16 and scale 1; give both the same"):  # fmt: skip
        load_map(str(path))
    path = broken(tmp_path, 'undefined_reads = "zero"', 'undefined_reads = "zeros"')
    with pytest.raises(RegisterMapError, match=r"unknown undefined_reads 'zeros'; did you mean"
                                               r" 'zero'\?"):  # fmt: skip
        load_map(str(path))
