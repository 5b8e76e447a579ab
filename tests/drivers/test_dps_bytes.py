"""Byte-exact Modbus RTU exchanges of the RDTech DPS supplies (regmaps/dps*.toml), from the
published register map (Ruideng "DPS5005 digital power communication protocol V1.2"): holding
registers 0x00 U-SET (V x 100), 0x01 I-SET (A x 1000, x 100 on the DPS5015/5020), 0x02 UOUT,
0x03 IOUT, 0x07 PROTECT, 0x08 CV/CC, 0x09 ONOFF, 0x0B MODEL, and the active preset's S-OVP 0x52
(V x 100), S-OCP 0x53 (as I-SET) and S-OPP 0x54 (W x 10); function codes 03 and 06."""

from __future__ import annotations

import pytest

from drivers.errors import DeviceNotFoundError, DeviceProtocolError, LimitError
from drivers.psu.regmap_device import MappedSupply
from drivers.registry import KINDS, OpenSpec
from drivers.transport.modbus import ModbusLink
from regmaps import load_map
from tests.drivers.scripted import Exchange, ScriptedSerialPeer, rtu


def dps(regmap: str, script: list[Exchange]) -> tuple[MappedSupply, ScriptedSerialPeer]:
    peer = ScriptedSerialPeer(script)
    link = ModbusLink(name="coil_y", path=peer.path, baudrate=9600, timeout_s=0.3, retries=1)
    return MappedSupply(link, load_map(regmap), name="coil_y"), peer


def echo(frame: str) -> Exchange:
    """A write (function 06) and its echo."""
    return Exchange(rtu(frame), rtu(frame))


def test_dps5005_identify_set_points_readback_and_safe() -> None:
    supply, peer = dps("dps5005", [
        # MODEL (0x0B) reads 5005 = 0x138D; whole frames written out, CRC included
        Exchange(bytes.fromhex("01 03 00 0B 00 01 F5 C8"), bytes.fromhex("01 03 02 13 8D 75 11")),
        Exchange(bytes.fromhex("01 06 00 00 04 B0 8A BE"), bytes.fromhex("01 06 00 00 04 B0 8A BE")),  # U-SET 12.00 V
        echo("01 06 00 01 05 DC"),  # I-SET 1.500 A
        echo("01 06 00 09 00 01"),  # ONOFF on
        Exchange(rtu("01 03 00 07 00 01"), rtu("01 03 02 00 00")),  # PROTECT: none
        Exchange(rtu("01 03 00 00 00 01"), rtu("01 03 02 04 B0")),  # U-SET 12.00 V
        Exchange(rtu("01 03 00 01 00 01"), rtu("01 03 02 05 DC")),  # I-SET 1.500 A
        Exchange(rtu("01 03 00 02 00 01"), rtu("01 03 02 02 58")),  # UOUT 6.00 V
        Exchange(rtu("01 03 00 03 00 01"), rtu("01 03 02 05 DC")),  # IOUT 1.500 A
        Exchange(rtu("01 03 00 09 00 01"), rtu("01 03 02 00 01")),  # ONOFF on
        Exchange(rtu("01 03 00 08 00 01"), rtu("01 03 02 00 01")),  # CV/CC: CC
        Exchange(rtu("01 03 00 04 00 01"), rtu("01 03 02 03 84")),  # POWER 9.00 W
        echo("01 06 00 09 00 00"),  # safe: output off, then I-SET 0
        echo("01 06 00 01 00 00"),
    ])  # fmt: skip
    try:
        assert supply.identify().model == "RDTech DPS5005"
        assert supply.set_voltage(12.0) == pytest.approx(12.0)
        assert supply.set_current(1.5) == pytest.approx(1.5)
        supply.set_output(True)
        r = supply.read()
        assert (r.v_set_v, r.i_set_a, r.v_out_v, r.i_out_a) == pytest.approx((12.0, 1.5, 6.0, 1.5))
        assert r.output_on and r.constant_current and r.protection == ""
        assert r.power_w == pytest.approx(9.0)
        supply.safe()
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []


def test_dps5005_as_a_load_channel() -> None:
    supply, peer = dps("dps5005", [
        echo("01 06 00 01 00 00"),  # I-SET 0
        echo("01 06 00 00 04 B0"),  # U-SET 12.00 V (compliance)
        echo("01 06 00 09 00 01"),  # ONOFF on
    ])  # fmt: skip
    try:
        supply.enable_as_load(12.0)
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []


def test_dps5015_counts_current_in_10_ma_and_checks_its_range() -> None:
    supply, peer = dps("dps5015", [echo("01 06 00 01 04 D2")])  # I-SET 12.34 A = 1234
    try:
        assert supply.max_current_a == 15.0 and supply.max_voltage_v == 50.0
        assert supply.set_current(12.34) == pytest.approx(12.34)
        with pytest.raises(LimitError, match=r"15.5 A is outside 0-15 A"):
            supply.set_current(15.5)
        with pytest.raises(LimitError, match=r"51 V is outside 0-50 V"):
            supply.set_voltage(51.0)
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []


def test_another_model_on_the_port_is_named() -> None:
    supply, peer = dps("dps5005", [
        Exchange(rtu("01 03 00 0B 00 01"), rtu("01 03 02 13 97")),  # MODEL 5015
    ])  # fmt: skip
    try:
        with pytest.raises(
            DeviceNotFoundError, match=r"'model' \(0x000b\) reads 5015, .*expects 5005"
        ):
            supply.identify()
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []


def test_the_registry_opens_it_at_its_factory_baud_rate() -> None:
    peer = ScriptedSerialPeer([echo("01 06 00 09 00 00")])
    spec = OpenSpec("load_bus", "modbus-rtu", {"path": peer.path, "regmap": "dps5005"})
    supply = KINDS["regmap-supply"].open(spec)
    try:
        assert supply.link._client.comm_params.baudrate == 9600  # the map's [device] baudrate
        supply.set_output(False)
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []


def test_dps5005_protection_levels_set_and_read_back_at_the_tables_scales() -> None:
    # M0 S-OVP 0x52 (V x 100), S-OCP 0x53 (A x 1000 on a 5 A model), S-OPP 0x54 (W x 10)
    supply, peer = dps("dps5005", [
        echo("01 06 00 52 05 28"),  # S-OVP 13.20 V = 1320
        echo("01 06 00 53 06 40"),  # S-OCP 1.600 A = 1600
        echo("01 06 00 54 02 5D"),  # S-OPP 60.5 W = 605
        Exchange(rtu("01 03 00 52 00 01"), rtu("01 03 02 05 28")),
        Exchange(rtu("01 03 00 53 00 01"), rtu("01 03 02 06 40")),
        Exchange(rtu("01 03 00 54 00 01"), rtu("01 03 02 02 5D")),
    ])  # fmt: skip
    try:
        levels = supply.set_protection_levels(ovp_v=13.2, ocp_a=1.6, opp_w=60.5)
        assert [(p.kind, p.value, p.unit) for p in levels] == [
            ("OVP", 13.2, "V"), ("OCP", 1.6, "A"), ("OPP", 60.5, "W")]  # fmt: skip
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []


def test_dps5015_ocp_counts_10_ma_and_a_level_not_taken_is_named() -> None:
    supply, peer = dps("dps5015", [
        echo("01 06 00 53 04 D2"),  # S-OCP 12.34 A = 1234 (A x 100 on the 15 A model)
        Exchange(rtu("01 03 00 52 00 01"), rtu("01 03 02 13 EC")),  # 51.00 V
        Exchange(rtu("01 03 00 53 00 01"), rtu("01 03 02 05 DC")),  # 15.00 A: not what was sent
        Exchange(rtu("01 03 00 54 00 01"), rtu("01 03 02 1D 4C")),  # 750.0 W
    ])  # fmt: skip
    try:
        with pytest.raises(DeviceProtocolError, match=r"OCP written as 12.34 A reads back 15 A"
                                                       r" \(register 's_ocp' \(0x0053\)\)"):  # fmt: skip
            supply.set_protection_levels(ocp_a=12.34)
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []
