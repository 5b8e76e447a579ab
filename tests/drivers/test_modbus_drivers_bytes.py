"""Byte-exact Modbus exchanges of the Riden, register-map and relay drivers (RTU on a pty, TCP on
loopback), including malformed, truncated and exception replies."""

from __future__ import annotations

import pytest

from drivers.errors import (
    DeviceError,
    DeviceProtocolError,
    DeviceRefusedError,
    DeviceTimeoutError,
    LimitError,
)
from drivers.psu.regmap_device import MappedSupply, PolarityRelay
from drivers.psu.riden import RidenSupply
from drivers.transport.modbus import GARBLED_EXTRA_ATTEMPTS, ModbusLink
from regmaps import load_map
from tests.drivers.scripted import Exchange, ScriptedSerialPeer, ScriptedTcpPeer, crc16, rtu

MODEL_RD6006P = rtu("01 03 02 EA A1")  # 60065


def riden_rtu(script: list[Exchange]) -> tuple[RidenSupply, ScriptedSerialPeer]:
    peer = ScriptedSerialPeer([Exchange(rtu("01 03 00 00 00 01"), MODEL_RD6006P), *script])
    link = ModbusLink(name="coil_x", path=peer.path, baudrate=115200, timeout_s=0.3, retries=1)
    return RidenSupply(link, name="coil_x"), peer


def test_riden_rtu_set_points_and_readback() -> None:
    readback = "01 03 16" + " 2E E0 3A 98 17 70 3A 98 00 00 00 00 00 00 00 00 00 00 00 01 00 01"
    supply, peer = riden_rtu([
        Exchange(rtu("01 03 00 00 00 04"), rtu("01 03 08 EA A1 00 00 30 39 00 8C")),
        Exchange(rtu("01 06 00 08 2E E0"), rtu("01 06 00 08 2E E0")),  # 12.000 V
        Exchange(rtu("01 06 00 09 3A 98"), rtu("01 06 00 09 3A 98")),  # 1.5000 A
        Exchange(rtu("01 06 00 12 00 01"), rtu("01 06 00 12 00 01")),  # output on
        Exchange(rtu("01 03 00 08 00 0B"), rtu(readback)),
        Exchange(rtu("01 06 00 12 00 00"), rtu("01 06 00 12 00 00")),  # safe: off, I 0, V 0
        Exchange(rtu("01 06 00 09 00 00"), rtu("01 06 00 09 00 00")),
        Exchange(rtu("01 06 00 08 00 00"), rtu("01 06 00 08 00 00")),
    ])  # fmt: skip
    try:
        ident = supply.identify()
        assert (ident.model, ident.serial, ident.firmware) == ("RD6006P", "12345", "1.40")
        assert supply.set_voltage(12.0) == pytest.approx(12.0)
        assert supply.set_current(1.5) == pytest.approx(1.5)
        supply.set_output(True)
        r = supply.read()
        assert (r.v_set_v, r.i_set_a, r.v_out_v, r.i_out_a) == pytest.approx((12.0, 1.5, 6.0, 1.5))
        assert r.output_on and r.constant_current and r.protection == ""
        supply.safe()
    finally:
        supply.link.close()
        peer.close()
    assert peer.mismatches == []


def test_riden_limits_are_checked_before_sending() -> None:
    supply, peer = riden_rtu([])
    try:
        with pytest.raises(LimitError, match=r"61 V is outside 0-60 V"):
            supply.set_voltage(61.0)
        with pytest.raises(LimitError, match="outside"):
            supply.set_current(-0.1)
    finally:
        supply.link.close()
        peer.close()
    assert peer.mismatches == []


def test_riden_exception_reply_is_refused_not_retried() -> None:
    supply, peer = riden_rtu([Exchange(rtu("01 06 00 08 2E E0"), rtu("01 86 03"))])
    try:
        with pytest.raises(
            DeviceRefusedError, match=r"coil_x at .* refused .*exception 3 \(illegal data value\)"
        ):
            supply.set_voltage(12.0)
    finally:
        supply.link.close()
        peer.close()
    assert peer.mismatches == []


@pytest.mark.parametrize(
    "reply",
    [
        rtu("01 03 02 EA A1")[:-2] + b"\x00\x00",  # bad CRC
        rtu("01 03 02 EA A1")[:3],  # truncated
        b"",  # silence
    ],
    ids=["bad-crc", "truncated", "silent"],
)
def test_riden_garbled_replies_are_retried_then_reported(reply: bytes) -> None:
    request = rtu("01 03 00 00 00 04")
    # retries=1: two attempts for silence; a device that answers, garbled, gets
    # GARBLED_EXTRA_ATTEMPTS more
    attempts = 2 if not reply else 2 + GARBLED_EXTRA_ATTEMPTS
    supply, peer = riden_rtu([Exchange(request, reply)] * attempts)
    try:
        with pytest.raises(
            DeviceError, match=rf"coil_x at /dev/pts/\d+: .*{attempts} attempts"
        ) as info:
            supply.identify()
        if reply:  # damaged replies: a noisy line, said so; the next request gets every retry
            assert isinstance(info.value, DeviceProtocolError) and "only damaged ones" in str(
                info.value
            )
            assert not supply.link.failed
        else:  # silence: a device that may be gone; the next request is tried once
            assert isinstance(info.value, DeviceTimeoutError) and "no reply" in str(info.value)
            assert supply.link.failed
    finally:
        supply.link.close()
        peer.close()
    assert peer.mismatches == []


def test_crc_helper_matches_the_modbus_reference_value() -> None:
    assert crc16(bytes.fromhex("01 03 00 00 00 01")) == bytes.fromhex("84 0A")


def test_riden_over_tcp() -> None:
    peer = ScriptedTcpPeer([
        (bytes.fromhex("01 03 00 00 00 01"), bytes.fromhex("01 03 02 EB 31")),  # 60209: unknown
    ])  # fmt: skip
    link = ModbusLink(name="coil_z", host="127.0.0.1", port=peer.port, timeout_s=0.5, retries=0)
    try:
        with pytest.raises(DeviceError, match=r"model id 60209 is not a known Riden"):
            RidenSupply(link, name="coil_z")
    finally:
        link.close()
        peer.close()
    assert peer.mismatches == []


def test_electronic_load_float32_over_tcp() -> None:
    peer = ScriptedTcpPeer([
        # remote control first (coil PC1, function 05), read back (function 01)
        (bytes.fromhex("01 05 05 00 FF 00"), bytes.fromhex("01 05 05 00 FF 00")),
        (bytes.fromhex("01 01 05 00 00 01"), bytes.fromhex("01 01 01 01")),
        (bytes.fromhex("01 10 0A 01 00 02 04 40 20 00 00"), bytes.fromhex("01 10 0A 01 00 02")),  # 2.5 A
        # CMD 1 = CC, by function 16 (the M97xx has no function 06), read back at SETMODE: 0xFF01
        (bytes.fromhex("01 10 0A 00 00 01 02 00 01"), bytes.fromhex("01 10 0A 00 00 01")),
        (bytes.fromhex("01 03 0B 04 00 01"), bytes.fromhex("01 03 02 FF 01")),
        (bytes.fromhex("01 10 0A 00 00 01 02 00 2A"), bytes.fromhex("01 10 0A 00 00 01")),  # 42: on
        (bytes.fromhex("01 03 0B 04 00 01"), bytes.fromhex("01 03 02 FF 01")),  # still CC
        (bytes.fromhex("01 03 0B 02 00 02"), bytes.fromhex("01 03 04 40 1F FF EF")),  # 2.49999 A
        (bytes.fromhex("01 10 0A 00 00 01 02 00 2B"), bytes.fromhex("01 10 0A 00 00 01")),  # 43: off
        (bytes.fromhex("01 10 0A 01 00 02 04 00 00 00 00"), bytes.fromhex("01 10 0A 01 00 02")),
        (bytes.fromhex("01 05 05 00 00 00"), bytes.fromhex("01 05 05 00 00 00")),  # local again
    ])  # fmt: skip
    link = ModbusLink(name="load", host="127.0.0.1", port=peer.port, timeout_s=0.5, retries=0)
    load = MappedSupply(link, load_map("maynuo-m97"), name="load")
    try:
        load.set_current(2.5)
        load.set_output(True)
        assert load._read(load.map.require("i_out")) == pytest.approx(2.49999, abs=1e-5)
        load.safe()
        with pytest.raises(LimitError):
            load.set_current(-1.0)  # a load is unipolar
    finally:
        load.close()
        peer.close()
    assert peer.mismatches == []


def test_polarity_relay_over_tcp() -> None:
    peer = ScriptedTcpPeer([
        (bytes.fromhex("01 06 00 02 00 01"), bytes.fromhex("01 06 00 02 00 01")),
        (bytes.fromhex("01 03 00 02 00 01"), bytes.fromhex("01 03 02 00 01")),  # read back
        (bytes.fromhex("01 03 00 02 00 01"), bytes.fromhex("01 03 02 00 01")),
        (bytes.fromhex("01 03 00 00 00 01"), bytes.fromhex("01 03 02 00 07")),  # not 0/1
    ])  # fmt: skip
    link = ModbusLink(name="polarity", host="127.0.0.1", port=peer.port, timeout_s=0.5, retries=0)
    relay = PolarityRelay(link, load_map("relay-h-bridge"))
    try:
        relay.set_polarity(2, -1)
        assert relay.polarity(2) == -1
        with pytest.raises(DeviceError, match="state 7 is not 0 or 1"):
            relay.polarity(0)
    finally:
        link.close()
        peer.close()
    assert peer.mismatches == []


def test_a_noisy_line_gets_more_attempts_and_then_the_answer() -> None:
    """Three damaged replies, then a good one: a device that answers is not given up after the
    link's own retries (retries=1 here) while the line is merely noisy."""
    request = rtu("01 03 00 00 00 04")
    damaged = rtu("01 03 08 EA A1 00 00 30 39 00 8C")[:-2] + b"\x00\x00"
    good = rtu("01 03 08 EA A1 00 00 30 39 00 8C")
    supply, peer = riden_rtu([Exchange(request, damaged)] * 3 + [Exchange(request, good)])
    try:
        assert supply.identify().serial == "12345"
        assert not supply.link.failed
    finally:
        supply.link.close()
        peer.close()
    assert peer.mismatches == []
