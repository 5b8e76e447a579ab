"""Byte-exact Modbus RTU exchanges of the Hanmatek HM310P / HM305P (regmaps/hm3*.toml), from
the published register table (mckenm/HanmaTekPSUCmd wiki): 0x0001 output, 0x0002 protection bit
mask, 0x0003 model, 0x0005 decimals (0x0233), 0x0010 V, 0x0011 A, 0x0030 V set (V x 100),
0x0031 A set (A x 1000), the protection levels OVP 0x0020 (V x 100), OCP 0x0021 (A x 1000) and
OPP 0x0022-23 (W x 100, 32-bit: the OEM table as a real HM310T confirmed it, github.com/
joeyda3rd/hm310t); function codes 03, 06 and 16."""

from __future__ import annotations

import pytest

from drivers.errors import DeviceNotFoundError, LimitError
from drivers.psu.regmap_device import MappedSupply
from drivers.transport.modbus import ModbusLink
from regmaps import load_map
from tests.drivers.scripted import Exchange, ScriptedSerialPeer, rtu


def hm(regmap: str, script: list[Exchange]) -> tuple[MappedSupply, ScriptedSerialPeer]:
    peer = ScriptedSerialPeer(script)
    link = ModbusLink(name="coil_z", path=peer.path, baudrate=9600, timeout_s=0.3, retries=1)
    return MappedSupply(link, load_map(regmap), name="coil_z"), peer


def echo(frame: str) -> Exchange:
    """A write (function 06) and its echo."""
    return Exchange(rtu(frame), rtu(frame))


def test_hm310p_identify_set_points_readback_and_safe() -> None:
    supply, peer = hm("hm310p", [
        # model (0x0003) reads 3010 = 0x0BC2, decimals (0x0005) 0x0233; whole frames, CRC included
        Exchange(bytes.fromhex("01 03 00 03 00 01 74 0A"), bytes.fromhex("01 03 02 0B C2 3E E5")),
        Exchange(rtu("01 03 00 04 00 01"), rtu("01 03 02 4B 50")),  # class 0x4B50
        Exchange(bytes.fromhex("01 03 00 05 00 01 94 0B"), bytes.fromhex("01 03 02 02 33 F9 31")),
        Exchange(bytes.fromhex("01 06 00 30 04 B0 8A B1"), bytes.fromhex("01 06 00 30 04 B0 8A B1")),  # 12.00 V
        echo("01 06 00 31 09 C4"),  # 2.500 A
        echo("01 06 00 01 00 01"),  # output on
        Exchange(rtu("01 03 00 02 00 01"), rtu("01 03 02 00 02")),  # protection: OCP
        Exchange(rtu("01 03 00 30 00 01"), rtu("01 03 02 04 B0")),  # V set 12.00
        Exchange(rtu("01 03 00 31 00 01"), rtu("01 03 02 09 C4")),  # A set 2.500
        Exchange(rtu("01 03 00 10 00 01"), rtu("01 03 02 00 00")),  # V 0.00 (tripped)
        Exchange(rtu("01 03 00 11 00 01"), rtu("01 03 02 00 00")),  # A 0.000
        Exchange(rtu("01 03 00 01 00 01"), rtu("01 03 02 00 00")),  # output off
        Exchange(rtu("01 03 00 12 00 02"), rtu("01 03 04 00 00 00 00")),  # 0.000 W
        echo("01 06 00 01 00 00"),  # safe: output off, then A set 0
        echo("01 06 00 31 00 00"),
    ])  # fmt: skip
    try:
        assert supply.identify().model == "Hanmatek HM310P"
        assert supply.set_voltage(12.0) == pytest.approx(12.0)
        assert supply.set_current(2.5) == pytest.approx(2.5)
        supply.set_output(True)
        r = supply.read()
        assert (r.v_set_v, r.i_set_a, r.v_out_v, r.i_out_a) == pytest.approx((12.0, 2.5, 0.0, 0.0))
        assert not r.output_on and not r.constant_current and r.protection == "OCP"
        assert r.power_w == 0.0
        supply.safe()
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []


def test_hm310p_as_a_load_channel() -> None:
    supply, peer = hm("hm310p", [
        echo("01 06 00 31 00 00"),  # A set 0
        echo("01 06 00 30 0B B8"),  # V set 30.00 V: the 48 V asked for, capped at the range
        echo("01 06 00 01 00 01"),  # output on
    ])  # fmt: skip
    try:
        supply.enable_as_load(48.0)
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []


def test_hm305p_range_and_model() -> None:
    supply, peer = hm("hm305p", [
        echo("01 06 00 31 13 88"),  # 5.000 A
        Exchange(rtu("01 03 00 03 00 01"), rtu("01 03 02 0B C2")),  # model 3010: an HM310P
    ])  # fmt: skip
    try:
        assert supply.set_current(5.0) == pytest.approx(5.0)
        with pytest.raises(LimitError, match=r"5.5 A is outside 0-5 A"):
            supply.set_current(5.5)
        with pytest.raises(
            DeviceNotFoundError, match=r"reads 3010, .*expects 305; is this a Hanmatek HM305P"
        ):
            supply.identify()
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []


def test_hm310p_protection_levels_at_the_tables_scales() -> None:
    # a real HM310T's dump: OVP 0x0020 = 1000 (V x 100), OCP 0x0021 = 1000 (A x 1000), OPP
    # 0x0022-23 = 0, 30000 (W x 100, high word first): 10.00 V, 1.000 A, 300.00 W
    supply, peer = hm("hm310p", [
        Exchange(rtu("01 03 00 20 00 01"), rtu("01 03 02 03 E8")),
        Exchange(rtu("01 03 00 21 00 01"), rtu("01 03 02 03 E8")),
        Exchange(rtu("01 03 00 22 00 02"), rtu("01 03 04 00 00 75 30")),
        # OPP 150.00 W = 15000 = 0x3A98: function 16, two registers, high word first
        Exchange(rtu("01 10 00 22 00 02 04 00 00 3A 98"), rtu("01 10 00 22 00 02")),
        Exchange(rtu("01 03 00 20 00 01"), rtu("01 03 02 03 E8")),
        Exchange(rtu("01 03 00 21 00 01"), rtu("01 03 02 03 E8")),
        Exchange(rtu("01 03 00 22 00 02"), rtu("01 03 04 00 00 3A 98")),
    ])  # fmt: skip
    try:
        assert [(p.kind, p.value) for p in supply.protection_levels()] == [
            ("OVP", 10.0), ("OCP", 1.0), ("OPP", 300.0)]  # fmt: skip
        levels = supply.set_protection_levels(opp_w=150.0)
        opp = levels[2]
        assert (opp.kind, opp.value, opp.register) == ("OPP", 150.0, "register 'opp' (0x0022)")
    finally:
        supply.close()
        peer.close()
    assert peer.mismatches == []
