"""HMR2300 on a pty, driven with raw pyserial bytes exactly as the datasheet describes."""

from __future__ import annotations

import struct
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import serial

from sim.cage import SimulatedCage
from sim.hmr2300 import Hmr2300

pytestmark = pytest.mark.realtime


def decode_binary(frame: bytes) -> np.ndarray:
    assert len(frame) == 7 and frame[6] == 0x0D
    return np.array(struct.unpack(">hhh", frame[:6]), float) / 150.0  # uT


def decode_ascii(frame: bytes) -> np.ndarray:
    assert len(frame) == 28 and frame.endswith(b"\r")
    text = frame.decode("ascii")
    return (
        np.array(
            [
                int(text[a:b].replace(",", "").replace(" ", ""))
                for a, b in ((0, 7), (9, 16), (18, 25))
            ],
            float,
        )
        / 150.0
    )


@pytest.fixture()
def port(devices: dict[str, Any], cage: SimulatedCage) -> Iterator[serial.Serial]:
    dev = devices["dut"]
    s = serial.Serial(dev["path"], dev["baudrate"], timeout=1.0)
    s.write(b"\x1b")  # stop any stream a previous test left running
    time.sleep(0.05)
    s.reset_input_buffer()
    yield s
    s.write(b"\x1b*00WE\r")
    s.read_until(b"\r")
    s.write(b"*00A\r")
    s.read_until(b"\r")
    s.reset_input_buffer()
    s.close()


def read_exactly(s: serial.Serial, n: int, deadline_s: float = 30.0) -> bytes:
    """``n`` bytes, or fewer if ``deadline_s`` (s, generous: a loaded machine) passes first."""
    data = b""
    deadline = time.monotonic() + deadline_s
    while len(data) < n and time.monotonic() < deadline:
        data += s.read(n - len(data))
    return data


def cmd(s: serial.Serial, text: str) -> bytes:
    """Send a command, return its reply line (waits up to 30 s: a loaded machine is slow)."""
    s.write(text.encode() + b"\r")
    reply = b""
    deadline = time.monotonic() + 30.0
    while not reply.endswith(b"\r") and time.monotonic() < deadline:
        reply += s.read_until(b"\r")
    return bytes(reply)


def test_identity_and_write_protection(port: serial.Serial) -> None:
    assert cmd(port, "*99ID=") == b"ID= 00\r"
    assert cmd(port, "*00#") == b"SER# 0123" + b" " * 12 + b"\r"  # 22 bytes, as the datasheet
    assert cmd(port, "*00A") == b"WE OFF\r"  # protected without WE
    assert cmd(port, "*00WE") == b"OK\r"
    assert cmd(port, "*00A") == b"ASCII ON\r"
    assert cmd(port, "*00B") == b"WE OFF\r"  # WE covers the next command only
    assert cmd(port, "*aaaaaaaaaaaaaaaa") == b"Re-enter\r"
    assert cmd(port, "*00XYZ") == b"Re-enter\r"
    port.write(b"*05P\r")  # another device's ID: silence
    assert port.read(1) == b""


def test_ascii_sample_matches_the_truth_model(port: serial.Serial, cage: SimulatedCage) -> None:
    port.write(b"*00P\r")
    m = decode_ascii(port.read(28))
    truth = cage.physics.magnetometers["dut"]
    expected = truth.truth_reading(
        cage.physics.field_ut(noise=False), cage.physics.load_currents(time.monotonic())
    )
    assert np.all(np.abs(m - expected) < 0.2), (m, expected)  # noise 0.02 uT, 1 count = 6.7 nT


def test_binary_frames_including_0x0d(port: serial.Serial, cage: SimulatedCage) -> None:
    assert cmd(port, "*00WE") == b"OK\r"
    assert cmd(port, "*00B") == b"BINARY ON\r"
    port.write(b"*00P\r")
    frame = port.read(7)
    m = decode_binary(frame)
    assert np.all(np.abs(m) < 200)
    # Force a reading whose low byte is 0x0D: a CR inside the frame must not split it.
    mag = cage.physics.magnetometers["dut"]
    mag.faults.stuck = True
    mag._last = np.array([0x0D / 150.0, 0x010D / 150.0, -1.0])
    try:
        port.write(b"*00P\r")
        frame = port.read(7)
    finally:
        mag.faults.stuck = False
    assert frame[:6].count(b"\r") >= 2 and frame[6] == 0x0D
    np.testing.assert_allclose(
        decode_binary(frame), [0x0D / 150.0, 0x010D / 150.0, -1.0], atol=1e-9
    )


def test_continuous_stream_rate_and_escape(port: serial.Serial, cage: SimulatedCage) -> None:
    device = cage.serial_devices["dut"]
    assert isinstance(device, Hmr2300)
    assert cmd(port, "*00WE") == b"OK\r"
    assert cmd(port, "*00B") == b"BINARY ON\r"
    assert cmd(port, "*00WE") == b"OK\r"
    assert cmd(port, "*00R=100") == b"OK\r"
    sent_a = device.samples_sent
    port.write(b"*00C\r")
    data = read_exactly(port, 7 * 50)
    port.write(b"\x1b")
    deadline = time.monotonic() + 30
    while device.streaming and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not device.streaming  # ESC stopped the stream
    sent_b, due_b = device.stream_clock
    assert sent_b == device.samples_sent and sent_b - sent_a >= 50
    data += read_exactly(port, 7 * (sent_b - sent_a) - len(data))  # every frame sent arrives
    assert port.read(1) == b""  # and nothing after the last one
    frames = [data[i : i + 7] for i in range(0, len(data), 7)]
    assert all(f[6] == 0x0D for f in frames)
    # The rate on the device's own sample clock (a descheduled reader cannot change it).
    assert (sent_b - sent_a - 1) / (due_b - device.stream_start_s) == pytest.approx(100, rel=0.01)
    assert cmd(port, "*00WE") == b"OK\r"
    assert cmd(port, "*00R=77") == b"Re-enter\r"  # not a datasheet rate


def test_query_zero_and_average(port: serial.Serial) -> None:
    q = cmd(port, "*00Q")
    assert q.startswith(b"ASCII ON") and b"ID= 00" in q
    assert cmd(port, "*00WE") == b"OK\r"
    assert cmd(port, "*00ZN") == b"ZERO ON\r"
    port.write(b"*00P\r")
    m = decode_ascii(port.read(28))
    assert np.all(np.abs(m) < 0.3)  # the current reading was stored as the zero
    assert cmd(port, "*00WE") == b"OK\r"
    assert cmd(port, "*00ZF") == b"ZERO OFF\r"
    assert cmd(port, "*00WE") == b"OK\r"
    assert cmd(port, "*00VN") == b"AVG ON\r"
    assert cmd(port, "*00WE") == b"OK\r"
    assert cmd(port, "*00VF") == b"AVG OFF\r"


def test_wrong_baud_rate_gets_no_answer(devices: dict[str, Any]) -> None:
    with serial.Serial(devices["dut"]["path"], 9600, timeout=0.3) as s:
        s.write(b"*99ID=\r")
        assert s.read(10) == b""
