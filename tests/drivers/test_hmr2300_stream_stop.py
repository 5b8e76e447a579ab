"""Stopping an HMR2300's stream (issue 53): the driver goes on only once the line has fallen silent
for longer than the gap between two frames, sending ESC again while frames keep coming, so bytes
still on their way are never read as the next command's reply; and a reply that is not the one
asked for is asked again like a damaged one.

The collision is the RS-485 variant's (half duplex: an ESC sent while a frame is on the pair is
lost), on the simulated sensor in simulated time: the ESC is put onto the line 3 ms into a frame,
exactly, every run. The unexpected reply is a scripted peer's (a stale streamed frame)."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

import timebase
from drivers.mag.hmr2300 import Hmr2300 as Hmr2300Driver
from drivers.transport import serial_port
from drivers.transport.serial_port import SerialPort
from sim.hmr2300 import Hmr2300
from sim.physics import Faults
from tests.drivers.scripted import Exchange, ScriptedSerialPeer
from timebase.wires import wires

pytestmark = pytest.mark.realtime

FIELD_UT = (20.0, -5.0, 45.0)
RATE_SPS = 10
FRAME_S = 7 * 10 / 9600  # a binary frame on the line at 9600 Bd


def test_an_esc_lost_in_a_collision_is_sent_again_until_the_stream_has_stopped() -> None:
    with timebase.simulated():
        sensor = Hmr2300(lambda _t: np.array(FIELD_UT), Faults(), baudrate=9600, half_duplex=True)
        driver = Hmr2300Driver(sensor.path, baudrate=9600, device_id=0)
        try:
            driver.set_binary(True)
            driver.set_rate(RATE_SPS)
            driver.start_stream()
            assert driver.read_stream(0.5) == [pytest.approx(FIELD_UT)]
            # the ESC goes out 3 ms after the next frame has begun: it collides with it
            slots = (timebase.monotonic() - sensor.stream_start_s) * RATE_SPS
            due = sensor.stream_start_s + math.ceil(slots) / RATE_SPS
            timebase.sleep(due + 0.003 - timebase.monotonic())
            t0 = timebase.monotonic()
            driver.stop_stream()
            waited_s = timebase.monotonic() - t0
            assert sensor.bytes_collided >= 1  # the first ESC was lost ...
            assert not sensor.streaming  # ... and the stream stopped all the same
            # silent for longer than the gap between two frames after the last one
            assert waited_s > 1 / RATE_SPS + FRAME_S
            driver.set_binary(False)  # answered at once: nothing stale on the line
            assert driver.read() == pytest.approx(FIELD_UT)
        finally:
            driver.close()
            sensor.close()


def test_a_stale_frame_read_as_the_serial_numbers_reply_is_asked_again() -> None:
    stale = struct.pack(">hhh", 366, 4096, -256) + b"\r"  # b'\x01n...': a streamed frame
    peer = ScriptedSerialPeer([
        Exchange(b"\x1b", b""),
        Exchange(b"*99ID=\r", b"ID= 07\r"),
        Exchange(b"*07#\r", stale),
        Exchange(b"*07#\r", b"SER# 0123            \r"),
        Exchange(b"*07F\r", b"S/W vers: 3.12            \r"),
    ])  # fmt: skip
    mag = Hmr2300Driver(peer.path, baudrate=19200, set_reset_auto=False)
    try:
        ident = mag.identify()
        assert (ident.serial, ident.firmware) == ("0123", "3.12")
    finally:
        mag.port.close()
        peer.close()
    assert peer.mismatches == []


def test_a_quiet_the_kernel_may_have_held_bytes_through_is_not_silence(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """ADR 0013: the kernel's terminal layer can hold received bytes back (USB-serial adapters and
    ptys alike). A sensor's last frame held for 80 ms must not end a 50 ms wait for silence and
    then be read as the next reply: the wait discards it and goes on until the line has really
    been quiet. (The stall is told to the port as the tty canary would measure it.)"""
    monkeypatch.setattr(
        serial_port, "tty_stall_s",
        lambda since, until=None: max(0.0, min(until or 0.08, 0.08) - since),
    )  # fmt: skip
    with timebase.simulated():
        end = wires().serve_serial("held", baud=9600).device

        def held_frame() -> None:
            timebase.sleep(0.08 - 7 * 10 / 9600)  # the frame arrives when the stall ends
            end.write(struct.pack(">hhh", 366, 4096, -256) + b"\r")

        port = SerialPort("simpipe://held", 9600, timeout_s=0.2, name="held")
        timebase.Thread(held_frame, daemon=True).start()
        port.drain_input(quiet_s=0.05)
        assert timebase.monotonic() == pytest.approx(0.08 + 0.05)
        assert port.read_available() == b""  # nothing stale left for the next reply
        port.close()
