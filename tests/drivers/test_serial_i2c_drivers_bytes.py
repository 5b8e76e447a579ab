"""Byte-exact exchanges of the HMR2300, ASCII-line, RM3100 and LIS3MDL drivers."""

from __future__ import annotations

import struct
import time

import pytest

from drivers.errors import (
    DeviceNotFoundError,
    DeviceProtocolError,
    DeviceRefusedError,
    DeviceTimeoutError,
)
from drivers.mag.ascii_line import AsciiLineMagnetometer, LineFormat
from drivers.mag.hmr2300 import Hmr2300, parse_ascii, parse_binary
from drivers.mag.lis3mdl import Lis3mdl
from drivers.mag.rm3100 import Rm3100
from tests.drivers.scripted import Exchange, ScriptedI2CBus, ScriptedSerialPeer

OPEN = [Exchange(b"\x1b", b""), Exchange(b"*99ID=\r", b"ID= 07\r"),
        Exchange(b"*07WE\r", b"OK\r"), Exchange(b"*07TN\r", b"S/R ON\r")]  # fmt: skip


def test_hmr2300_identity_modes_and_samples() -> None:
    binary = struct.pack(">hhh", 0x0D, 0x010D, -150) + b"\r"  # two 0x0D bytes inside the data
    peer = ScriptedSerialPeer([
        *OPEN,
        Exchange(b"*07#\r", b"SER# 0123\r"),
        Exchange(b"*07F\r", b"S/W vers: 3.12\r"),
        Exchange(b"*07P\r", b"  3,000  - 0,750    6,750  \r"),
        Exchange(b"*07WE\r", b"OK\r"),
        Exchange(b"*07B\r", b"BINARY ON\r"),
        Exchange(b"*07P\r", binary),
        Exchange(b"*07WE\r", b"OK\r"),
        Exchange(b"*07R=154\r", b"OK\r"),
    ])  # fmt: skip
    mag = Hmr2300(peer.path, baudrate=19200)
    try:
        assert mag.device_id == 7
        ident = mag.identify()
        assert (ident.serial, ident.firmware) == ("0123", "3.12")
        assert mag.read() == pytest.approx((20.0, -5.0, 45.0))  # 3000 counts = 0.2 G = 20 uT
        mag.set_binary(True)
        assert mag.read() == pytest.approx((13 / 150, 269 / 150, -1.0))
        mag.set_rate(154)
        with pytest.raises(ValueError, match="77 sps"):
            mag.set_rate(77)
    finally:
        mag.port.close()
        peer.close()
    assert peer.mismatches == []


def test_hmr2300_stream_resyncs_on_the_stride_never_on_cr() -> None:
    good = [struct.pack(">hhh", 13, 3341, -13) + b"\r" for _ in range(6)]  # 0x0D everywhere
    stream = good[0] + good[1] + b"\x42\x17" + good[2] + good[3] + good[4] + good[5]
    peer = ScriptedSerialPeer([
        *OPEN,
        Exchange(b"*07WE\r", b"OK\r"),
        Exchange(b"*07B\r", b"BINARY ON\r"),
        Exchange(b"*07C\r", stream),
        Exchange(b"\x1b", b""),
    ])  # fmt: skip
    mag = Hmr2300(peer.path, baudrate=19200)
    try:
        mag.set_binary(True)
        mag.start_stream()
        frames: list[tuple[float, float, float]] = []
        deadline = time.monotonic() + 2
        while len(frames) < 6 and time.monotonic() < deadline:
            frames += mag.read_stream(0.2)
        mag.stop_stream()
    finally:
        mag.port.close()
        peer.close()
    assert len(frames) == 6 and all(
        f == pytest.approx((13 / 150, 3341 / 150, -13 / 150)) for f in frames
    )
    assert mag.resyncs >= 1
    assert mag.samples_lost == 1  # the two stray bytes: one frame cut short
    assert peer.mismatches == []


def test_hmr2300_refusals_and_truncated_sample() -> None:
    peer = ScriptedSerialPeer([
        *OPEN,
        # the pair is asked again (a damaged line may have eaten the first WE): refused 3 times
        *[Exchange(b"*07WE\r", b"OK\r"), Exchange(b"*07A\r", b"WE OFF\r")] * 3,
        Exchange(b"*07P\r", b"  3,000  - 0,7"),  # truncated, then silence (3 attempts)
        Exchange(b"*07P\r", b""),
        Exchange(b"*07P\r", b""),
    ])  # fmt: skip
    mag = Hmr2300(peer.path, baudrate=19200, timeout_s=0.2)
    try:
        with pytest.raises(DeviceRefusedError, match="needs write enable"):
            mag.set_binary(False)
        with pytest.raises(
            DeviceTimeoutError, match=r"HMR2300 on /dev/pts/\d+: got \d+ of 28 bytes"
        ):
            mag.read()
    finally:
        mag.port.close()
        peer.close()


def test_hmr2300_parsers_reject_damage() -> None:
    assert parse_ascii(b" 30,000  -30,000  + 0,001  \r") == pytest.approx((200.0, -200.0, 1 / 150))
    with pytest.raises(DeviceProtocolError):
        parse_binary(b"\x00\x01\x02\x03\x04\x05\x0a")
    with pytest.raises(DeviceProtocolError):
        parse_ascii(b"  3,0x0  - 0,750    6,750  \r")


def test_hmr2300_opening_turns_automatic_set_reset_on_and_a_scan_leaves_it() -> None:
    """Issue 51: a perming step killed with automatic set/reset off; the next session's opening
    sequence turns it on (``*ddWE``, ``*ddTN`` answered ``S/R ON``) before anything else, and a
    refusal there is the opening's error. A bring-up scan (``set_reset_auto=False``) sends neither."""
    peer = ScriptedSerialPeer([
        Exchange(b"\x1b", b""),
        Exchange(b"*99ID=\r", b"ID= 07\r"),
        Exchange(b"*07WE\r", b"OK\r"),
        Exchange(b"*07TN\r", b"S/R ON\r"),
        Exchange(b"*07#\r", b"SER# 0123\r"),
        Exchange(b"*07F\r", b"S/W vers: 3.12\r"),
    ])  # fmt: skip
    mag = Hmr2300(peer.path, baudrate=19200)
    try:
        assert mag.identify().serial == "0123"
    finally:
        mag.port.close()
        peer.close()
    assert peer.mismatches == []
    peer = ScriptedSerialPeer([
        Exchange(b"\x1b", b""),
        *[Exchange(b"*03WE\r", b"OK\r"), Exchange(b"*03TN\r", b"WE OFF\r")] * 3,
    ])  # fmt: skip
    with pytest.raises(DeviceRefusedError, match="'TN' needs write enable"):
        Hmr2300(peer.path, baudrate=19200, device_id=3, timeout_s=2.0)  # the peer answers at once
    peer.close()
    assert peer.mismatches == []
    peer = ScriptedSerialPeer([
        Exchange(b"\x1b", b""),
        Exchange(b"*99ID=\r", b"ID= 07\r"),
        Exchange(b"*07#\r", b"SER# 0123\r"),
        Exchange(b"*07F\r", b"S/W vers: 3.12\r"),
    ])  # fmt: skip
    mag = Hmr2300(peer.path, baudrate=19200, set_reset_auto=False)
    try:
        assert mag.identify().serial == "0123"
    finally:
        mag.port.close()
        peer.close()
    assert peer.mismatches == []


def test_hmr2300_not_an_hmr2300() -> None:
    peer = ScriptedSerialPeer([Exchange(b"\x1b", b""), Exchange(b"*99ID=\r", b"HELLO\r")])
    with pytest.raises(DeviceNotFoundError, match="is it an HMR2300"):
        Hmr2300(peer.path)
    peer.close()


def test_ascii_line_burst_says_which_lines_were_lost() -> None:
    """A garbled line is a sample the sensor sent: the burst says it was lost before the next,
    and a line that ran into the next (its terminator lost) stands for two."""
    peer = ScriptedSerialPeer([
        Exchange(b"", b"1.0 2.0 3.0\n", delay_s=0.3),
        Exchange(b"", b"1.5 2.5 3.5\n\x00garbage\n4.0 5.0 6.0\n1.0 2.0 3.01.0 2.0 3.0\n7.0 8.0 9.0\n"),
    ])  # fmt: skip
    mag = AsciiLineMagnetometer(peer.path, baudrate=115200, max_bad_lines=3)
    try:
        assert mag.read() == (1.0, 2.0, 3.0)
        burst: list[tuple[float, float, float]] = []
        deadline = time.monotonic() + 2
        while len(burst) < 3 and time.monotonic() < deadline:
            burst = mag.read_burst()
        assert burst == [(1.5, 2.5, 3.5), (4.0, 5.0, 6.0), (7.0, 8.0, 9.0)]
        assert mag.lost_before == (0, 1, 2)
    finally:
        mag.close()
        peer.close()


def test_ascii_line_formats_and_garbage() -> None:
    peer = ScriptedSerialPeer([
        Exchange(b"", b"12.5 -3.25 40.0\n", delay_s=0.3),  # pyserial flushes input on open
        Exchange(b"", b"\x00\xffgarbage\n"),
        Exchange(b"", b"1.0 2.0 3.0\n"),
        Exchange(b"", b"x\ny\nz\nw\n"),
    ])  # fmt: skip
    mag = AsciiLineMagnetometer(peer.path, baudrate=115200, max_bad_lines=3)
    try:
        assert mag.read() == (12.5, -3.25, 40.0)
        assert mag.read() == (1.0, 2.0, 3.0)
        assert mag.bad_lines == 1
        with pytest.raises(DeviceProtocolError, match="4 unreadable lines in a row"):
            mag.read()
    finally:
        mag.close()
        peer.close()
    csv = LineFormat(delimiter=",", columns=(1, 2, 3), scale_to_ut=0.001)
    assert csv.parse(b"1024,19500,-1200,44800,49000\r\n") == pytest.approx((19.5, -1.2, 44.8))


def test_rm3100_poll_and_continuous_bytes() -> None:
    raw = (
        (75 * 20).to_bytes(3, "big", signed=True)
        + (-75 * 5).to_bytes(3, "big", signed=True)
        + (0).to_bytes(3, "big")
    )
    bus = ScriptedI2CBus([
        (0x20, b"\x36", 1, b"\x22"),  # REVID
        (0x20, b"\x04\x00\xc8\x00\xc8\x00\xc8", 0, b""),  # CC = 200 on x, y, z
        (0x20, b"\x00\x70", 0, b""),  # POLL
        (0x20, b"\x34", 1, b"\x00"),  # STATUS: not ready
        (0x20, b"\x34", 1, b"\x80"),  # DRDY
        (0x20, b"\x24", 9, raw),
        (0x20, b"\x0b\x95", 0, b""),  # TMRC 75 Hz
        (0x20, b"\x01\x79", 0, b""),  # CMM: start, DRDM = 10, x y z
        (0x20, b"\x01\x00", 0, b""),
    ])  # fmt: skip
    rm = Rm3100(bus, 0x20)
    x, y, z = rm.read()
    gain = 0.3671 * 200 + 1.5  # 74.92 counts/uT
    assert (x, y, z) == pytest.approx((1500 / gain, -375 / gain, 0.0))
    assert rm.start_continuous(0x95) == 75.0
    rm.stop_continuous()
    assert bus.mismatches == [] and bus.script == []


def test_rm3100_nack_and_wrong_part() -> None:
    with pytest.raises(DeviceNotFoundError, match=r"no acknowledge \(NACK\) after 3 attempts"):
        Rm3100(ScriptedI2CBus([], nack_addresses={0x21}), 0x21)
    with pytest.raises(DeviceNotFoundError, match="REVID 0x33"):
        Rm3100(ScriptedI2CBus([(0x20, b"\x36", 1, b"\x33")]), 0x20)


def test_lis3mdl_configuration_and_little_endian_auto_increment() -> None:
    bus = ScriptedI2CBus([
        (0x1C, b"\x0f", 1, b"\x3d"),  # WHO_AM_I
        (0x1C, b"\x20\x7c", 0, b""),
        (0x1C, b"\x21\x00", 0, b""),  # +-4 G
        (0x1C, b"\x23\x0c", 0, b""),
        (0x1C, b"\x22\x00", 0, b""),
        (0x1C, b"\x27", 1, b"\x08"),  # ZYXDA
        (0x1C, b"\xa8", 6, struct.pack("<hhh", 6842, -3421, 0)),  # 0x28 | 0x80
        (0x1C, b"\x22\x03", 0, b""),  # safe: power down
    ])  # fmt: skip
    mag = Lis3mdl(bus, 0x1C)
    assert mag.read() == pytest.approx((100.0, -50.0, 0.0))
    mag.safe()
    assert bus.mismatches == [] and bus.script == []
