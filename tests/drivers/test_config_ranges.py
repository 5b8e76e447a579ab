"""Impossible device settings in a rig configuration are one-line errors naming the file, the device
section, the value, the accepted range and the fix. The ranges live in the registry's Params."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.config_keys import Param
from drivers.registry import KINDS, TRANSPORTS, transport_param
from rig.cli import main
from rig.config import load_rig_config
from rig.errors import UserInputError

TCP = 'kind = "riden-rd60xx"\nprotocol = "modbus-tcp"\nhost = "192.168.1.50"\nport = 502\n'
RTU = 'kind = "riden-rd60xx"\nprotocol = "modbus-rtu"\npath = "/dev/ttyUSB0"\n'
HMR = 'kind = "hmr2300"\nprotocol = "serial"\npath = "/dev/ttyUSB1"\n'


def write(tmp_path: Path, device: str) -> Path:
    p = tmp_path / "rig.toml"
    p.write_text(f"[devices.coil_x]\n{device}", encoding="utf-8")
    return p


@pytest.mark.parametrize(
    ("device", "message"),
    [
        (TCP.replace("502", "70000"),
         r"\.port: 70000 is outside 1-65535 \(a TCP port\); write the port the device listens on"),
        (TCP.replace("502", "0"), r"\.port: 0 is outside 1-65535"),
        (TCP.replace('"192.168.1.50"', '" "'), r"\.host: must not be empty; write .*host = "),
        (TCP + "device_id = 256\n",
         r"\.device_id: 256 is outside 0-255 \(a Modbus TCP unit id: .*255 or 0.*\); write the"
         r" Modbus address set on the device"),
        (TCP + "timeout_s = 0\n", r"\.timeout_s: must be more than 0, got 0; write the seconds"),
        (TCP + "timeout_s = nan\n", r"\.timeout_s: nan is not a finite number; write"),
        (TCP + "timeout_s = inf\n", r"\.timeout_s: inf is not a finite number"),
        (RTU + "device_id = 0\n",
         r"\.device_id: 0 is outside 1-247 \(a Modbus RTU address: 0 is the broadcast address,"
         r" which no device answers; 248-255 are reserved\); write the Modbus address"),
        (RTU + "device_id = 248\n", r"\.device_id: 248 is outside 1-247"),
        (RTU + "baudrate = 11520\n",
         r"\.baudrate: 11520 is not a standard baud rate \(did you mean 115200\?\): 300, .*"
         r" 115200, .*; write the rate set on the device"),
        (RTU + "baudrate = -9600\n", r"\.baudrate: -9600 is not a standard baud rate: "),
        (RTU + 'parity = "n"\n', r"\.parity: 'n' is not a parity \(none, even, odd\): N, E or O"),
        (RTU + "max_current_a = -1.0\n", r"\.max_current_a: must be more than 0, got -1"),
        (HMR + "device_id = 99\n", r"\.device_id: 99 is outside 0-98 \(HMR2300 ids; 99 is its"),
        (HMR + "baudrate = 9601\n", r"\.baudrate: 9601 is not a standard baud rate \(did you mean 9600"),
        ('kind = "rm3100"\nprotocol = "i2c"\naddress = 0x80\n', r"\.address: 128 is outside 8-119 \(7-bit I2C addresses 0x08-0x77"),
    ],
)  # fmt: skip
def test_impossible_values_are_one_line_errors(tmp_path: Path, device: str, message: str) -> None:
    with pytest.raises(UserInputError, match=r"^\S*rig.toml: \[devices.coil_x\]" + message) as info:
        load_rig_config(write(tmp_path, device))
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "device",
    [
        TCP + "device_id = 255\n",  # a device on the network itself (the TCP spec's "no unit")
        TCP + "device_id = 0\n",
        TCP + "device_id = 247\ntimeout_s = 1.5\n",
        RTU + 'device_id = 247\nbaudrate = 9600\nparity = "E"\n',
        HMR + "device_id = 0\nbaudrate = 19200\n",
        'kind = "rm3100"\nprotocol = "i2c"\naddress = 0x20\nbus = "sim"\n',
    ],
)
def test_values_in_range_load(tmp_path: Path, device: str) -> None:
    assert load_rig_config(write(tmp_path, device)).devices["coil_x"].params


def test_a_modbus_id_range_depends_on_the_transport() -> None:
    tcp, rtu = (
        transport_param("modbus-tcp", "device_id"),
        transport_param("modbus-rtu", "device_id"),
    )
    assert (tcp.problem(0), tcp.problem(255)) == (None, None)
    assert rtu.problem(0) is not None and rtu.problem(248) is not None
    assert rtu.problem(1) is None and rtu.problem(247) is None


def test_every_number_a_device_takes_has_a_range_or_is_checked_finite() -> None:
    params: list[Param] = [p for ps in TRANSPORTS.values() for p in ps]
    params += [p for k in KINDS.values() for p in k.params]
    for p in params:
        if p.types == (int, float):
            assert p.problem(float("nan")) is not None, p.name
        if p.name in ("port", "device_id", "baudrate", "timeout_s", "address"):
            assert p.accepted, p.name


def test_rig_check_with_an_impossible_port_says_so_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = write(tmp_path, TCP.replace("502", "70000"))
    assert main(["-q", "check", "smoke", "--rig", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"rig: error: {cfg}: [devices.coil_x].port: 70000 is outside 1-65535 (a TCP port); write"
        " the port the device listens on, e.g. port = 502 (Modbus TCP's own)"
    )


def test_devices_scan_refuses_an_impossible_port(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["-q", "devices", "scan", "--only-given", "--tcp", "127.0.0.1:70000"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "rig: error: --tcp 127.0.0.1:70000: port 70000 is outside 1-65535 (a TCP port); write the"
        " port the device listens on, e.g. --tcp 192.168.1.50:502"
    )
