"""The kernel's terminal layer can hold serial bytes back for seconds on a busy computer (its flip
buffer worker waits for a CPU); a serial timeout must not count that time against the instrument.
The canary's bookkeeping is checked with known stalls, and the serial port and the Modbus RTU
client are checked on real ptys with a stall reported while the device's reply is held back."""

from __future__ import annotations

import os
import threading
import time
import tty
from collections.abc import Callable, Iterator

import pytest

from drivers.errors import DeviceTimeoutError
from drivers.transport import modbus, serial_port, tty_watch
from drivers.transport.modbus import ModbusLink
from drivers.transport.serial_port import SerialPort
from drivers.transport.tty_watch import TOLERANCE_S, TtyWatch
from tests.drivers.scripted import crc16

pytestmark = pytest.mark.realtime


def test_stall_is_the_overlap_of_recorded_spans_with_the_window() -> None:
    watch = TtyWatch()
    for spans, measure in ((watch._possible, watch.stalled_s), (watch._seen, watch.seen_stalled_s)):
        with watch._lock:  # replace what the canary saw with known spans
            spans.clear()
            watch._in_flight_since = None
        watch._note(spans, 100.0, 100.5)
        watch._note(spans, 100.51, 101.0)  # adjacent looks: one span
        watch._note(spans, 102.0, 102.5)
        assert len(spans) == 2
        assert measure(99.0, 103.0) == pytest.approx(1.5)
        assert measure(100.5, 102.25) == pytest.approx(0.75)
        assert measure(101.0, 102.0) == 0.0


def test_an_overdue_canary_byte_is_a_possible_stall_going_on() -> None:
    watch = TtyWatch()
    now = time.monotonic()
    with watch._lock:
        watch._possible.clear()
        watch._in_flight_since = now - 0.4
    assert watch.stalled_s(now - 1.0, now) == pytest.approx(0.4 - TOLERANCE_S, abs=1e-6)


def test_a_canary_that_was_itself_descheduled_counts_no_stall() -> None:
    """The interpreter lock held by a busy thread of our own keeps the canary from looking: that
    is this process's stall, not the terminal layer's, and is not counted as seen."""
    watch = TtyWatch()
    time.sleep(0.2)
    t0 = time.monotonic()
    end = t0 + 0.5
    while time.monotonic() < end:  # pure Python: holds the interpreter lock between switches
        sum(range(1000))
    assert watch.seen_stalled_s(t0) < TOLERANCE_S


def test_the_canary_runs_and_sees_its_bytes_arrive() -> None:
    watch = tty_watch.tty_watch()
    assert watch is tty_watch.tty_watch()  # one per process
    deadline = time.monotonic() + 10
    while watch.worst_s == 0.0 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert watch.running and watch.worst_s > 0.0


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


def stall_until(t_end: float) -> Callable[[float, float | None], float]:
    """A terminal layer that holds everything back until ``t_end`` (monotonic s), on top of the
    stalls the real canary sees (on a busy computer the test's own pty stalls too)."""
    real = tty_watch.tty_stall_s

    def stalled(since: float, until: float | None = None) -> float:
        end = time.monotonic() if until is None else until
        return max(max(0.0, min(end, t_end) - since), real(since, until))

    return stalled


def _reply_after(master: int, delay_s: float, data: bytes) -> None:
    def send() -> None:
        time.sleep(delay_s)
        os.write(master, data)

    threading.Thread(target=send, daemon=True).start()


def test_serial_read_waits_out_a_terminal_stall(
    pty_pair: tuple[int, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    master, path = pty_pair
    port = SerialPort(path, 9600, timeout_s=0.3, name="probe")
    try:
        # without a stall, 0.3 s means 0.3 s
        _reply_after(master, 0.8, b"late\r")
        with pytest.raises(DeviceTimeoutError):
            port.read_until(b"\r")
        time.sleep(0.7)
        port.drain_input()
        # the same late reply while the kernel held bytes back for 0.9 s: taken
        monkeypatch.setattr(serial_port, "tty_stall_s", stall_until(time.monotonic() + 0.9))
        _reply_after(master, 0.8, b"held\r")
        assert port.read_until(b"\r") == b"held\r"
    finally:
        port.close()


def test_modbus_rtu_attempt_waits_out_a_terminal_stall(
    pty_pair: tuple[int, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    master, path = pty_pair
    link = ModbusLink(name="psu", path=path, baudrate=115200, device_id=1, timeout_s=0.3,
                      retries=0)  # fmt: skip
    try:
        reply = b"\x01\x03\x04\x00\x07\x00\x09"
        monkeypatch.setattr(modbus, "tty_stall_s", stall_until(time.monotonic() + 1.0))
        _reply_after(master, 0.9, reply + crc16(reply))
        assert link.read_registers(8, 2) == [7, 9]
        request = os.read(master, 64)
        assert request[:2] == b"\x01\x03"
        assert len(request) == 8  # asked once: the stall was not a silent device
    finally:
        link.close()
