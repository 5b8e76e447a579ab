"""Byte-exact Modbus RTU exchanges of the RTD module map (regmaps/rtd-module.toml): the
temperature as a signed 16-bit holding register 0x0000 in tenths of a degree C, function 03; a
negative temperature, and an open sensor's sentinel refused in one line."""

from __future__ import annotations

import pytest

from drivers.errors import DeviceProtocolError
from drivers.psu.regmap_device import MappedThermometer
from drivers.transport.modbus import ModbusLink
from regmaps import RegisterMapError, load_map
from tests.drivers.scripted import Exchange, ScriptedSerialPeer, rtu


def test_rtd_module_reads_degrees_c_and_refuses_an_open_sensor() -> None:
    peer = ScriptedSerialPeer([
        Exchange(rtu("01 03 00 00 00 01"), rtu("01 03 02 00 FD")),  # 253 -> 25.3 C
        Exchange(rtu("01 03 00 00 00 01"), rtu("01 03 02 FF 9C")),  # -100 -> -10.0 C
        Exchange(rtu("01 03 00 00 00 01"), rtu("01 03 02 80 00")),  # -32768: open RTD
    ])  # fmt: skip
    link = ModbusLink(name="dut_temp", path=peer.path, baudrate=9600, timeout_s=0.3, retries=1)
    thermometer = MappedThermometer(link, load_map("rtd-module"), name="dut_temp")
    try:
        assert thermometer.read_temperature_c() == pytest.approx(25.3)
        assert thermometer.read_temperature_c() == pytest.approx(-10.0)
        with pytest.raises(DeviceProtocolError, match=r"dut_temp .*-3276\.8 degrees C.*connected"):
            thermometer.read_temperature_c()
    finally:
        thermometer.close()
        peer.close()
    assert peer.mismatches == []


def test_a_supply_map_is_no_thermometer() -> None:
    with pytest.raises(RegisterMapError, match="not a thermometer"):
        MappedThermometer(None, load_map("maynuo-m97"))  # type: ignore[arg-type]
