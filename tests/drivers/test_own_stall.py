"""Timeouts measure the instrument, not our scheduler: a reader that was stopped (SIGSTOP stands in
for a busy computer) past its deadline while the reply arrived must take the reply, not time out
and throw it away. Real ptys, real processes, real wire bytes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import tty

import pytest

from tests.drivers.scripted import crc16
from tests.waiting import wait_until

pytestmark = pytest.mark.realtime

READER = r"""
import sys, time
from drivers.transport.serial_port import SerialPort
port = SerialPort(sys.argv[1], 9600, timeout_s=0.3, name="probe")
print("ready", flush=True)
print(port.read_until(b"\r").decode().strip(), flush=True)
"""

MODBUS = r"""
import sys
from drivers.transport.modbus import ModbusLink
link = ModbusLink(name="psu", path=sys.argv[1], baudrate=115200, device_id=1, timeout_s=2.0)
print("ready", flush=True)
print(link.read_registers(8, 2), flush=True)
"""


@pytest.fixture
def pty_pair() -> tuple[int, str]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    path = os.ttyname(slave)
    yield master, path
    os.close(master)
    os.close(slave)


def _start(code: str, path: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", code, path], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "ready"
    return proc


def _read_request(master: int, n: int, timeout_s: float = 10.0) -> bytes:
    buf = b""
    deadline = time.monotonic() + timeout_s
    while len(buf) < n and time.monotonic() < deadline:
        try:
            buf += os.read(master, 256)
        except BlockingIOError:
            time.sleep(0.01)
    return buf


def test_a_serial_reply_that_came_while_we_were_stopped_is_taken(
    pty_pair: tuple[int, str],
) -> None:
    master, path = pty_pair
    proc = _start(READER, path)
    time.sleep(0.05)  # the reader is in its 0.3 s wait
    proc.send_signal(signal.SIGSTOP)
    time.sleep(0.6)  # the reader's deadline passes while it cannot run
    os.write(master, b"SER# 0123\r")  # the instrument answered meanwhile
    proc.send_signal(signal.SIGCONT)
    out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0 and out.strip() == "SER# 0123"


def test_a_real_timeout_is_still_a_timeout(pty_pair: tuple[int, str]) -> None:
    _, path = pty_pair
    proc = subprocess.run([sys.executable, "-c", READER, path], capture_output=True, text=True,
                          timeout=20)  # fmt: skip
    assert proc.returncode != 0
    assert "no complete reply within 0.3 s" in proc.stderr


def test_a_modbus_rtu_reply_that_came_while_we_were_stopped_is_taken(
    pty_pair: tuple[int, str],
) -> None:
    master, path = pty_pair
    os.set_blocking(master, False)
    proc = _start(MODBUS, path)
    request = _read_request(master, 8)
    assert request[:6] == bytes([1, 3, 0, 8, 0, 2]), request.hex()
    # the client is waiting for the reply (2 s: room for this test to be descheduled between
    # reading the request and stopping it, on a busy machine)
    proc.send_signal(signal.SIGSTOP)
    time.sleep(2.5)  # longer than its timeout
    body = bytes([1, 3, 4, 0x12, 0x34, 0x56, 0x78])
    os.write(master, body + crc16(body))
    proc.send_signal(signal.SIGCONT)
    out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0, out
    assert out.strip() == str([0x1234, 0x5678])
    # one request only: the reply was not discarded and the request sent again
    assert _read_request(master, 1, timeout_s=0.3) == b""


def test_a_modbus_rtu_reply_in_pieces_with_a_stall_between_is_taken(
    pty_pair: tuple[int, str],
) -> None:
    master, path = pty_pair
    os.set_blocking(master, False)
    proc = _start(MODBUS, path)
    assert _read_request(master, 8)[:2] == bytes([1, 3])
    body = bytes([1, 3, 4, 0x12, 0x34, 0x56, 0x78])
    frame = body + crc16(body)
    os.write(master, frame[:4])  # the first piece; the kernel delivers the rest later
    time.sleep(0.1)
    proc.send_signal(signal.SIGSTOP)
    time.sleep(0.6)
    os.write(master, frame[4:])
    proc.send_signal(signal.SIGCONT)
    out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0, out
    assert out.strip() == str([0x1234, 0x5678])
    assert _read_request(master, 1, timeout_s=0.3) == b""  # asked once


def test_rtu_reply_lengths() -> None:
    from drivers.transport.modbus import rtu_reply_length

    assert rtu_reply_length(b"\x01") is None
    assert rtu_reply_length(bytes([1, 3])) is None  # byte count not yet there
    assert rtu_reply_length(bytes([1, 3, 4])) == 9
    assert rtu_reply_length(bytes([1, 6])) == 8 and rtu_reply_length(bytes([1, 16])) == 8
    assert rtu_reply_length(bytes([1, 0x83])) == 5
    assert rtu_reply_length(bytes([1, 43])) is None


STALE = r"""
import sys
from drivers.transport.modbus import ModbusLink
link = ModbusLink(name="psu", path=sys.argv[1], baudrate=115200, device_id=1, timeout_s=0.5)
print("ready", flush=True)
print(link.read_registers(8, 2), link.stale_replies, flush=True)
"""


def test_a_late_reply_to_an_earlier_request_is_recognized_and_the_request_repeated(
    pty_pair: tuple[int, str],
) -> None:
    master, path = pty_pair
    os.set_blocking(master, False)
    proc = _start(STALE, path)
    assert _read_request(master, 8)[:6] == bytes([1, 3, 0, 8, 0, 2])
    stale = bytes([1, 3, 2, 0x00, 0x07])  # one register: the answer to some earlier read
    os.write(master, stale + crc16(stale))
    assert _read_request(master, 8)[:6] == bytes([1, 3, 0, 8, 0, 2])  # asked again
    body = bytes([1, 3, 4, 0x12, 0x34, 0x56, 0x78])
    os.write(master, body + crc16(body))
    out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0, out
    assert out.strip() == f"{[0x1234, 0x5678]} 1"


def arrived(client: object, size: int) -> None:
    """Until ``size`` bytes written to the master side are readable on the client's side: the
    kernel hands pty bytes over on a worker thread, and on a loaded machine that took over 50 ms
    (a fixed sleep here failed beside a second copy of the suite, load 11)."""
    port = client.socket  # type: ignore[attr-defined]
    wait_until(lambda: int(port.in_waiting) >= size, 10.0, f"{size} bytes at the client's port")


def test_a_late_reply_answers_the_retry_of_the_same_request(pty_pair: tuple[int, str]) -> None:
    """A reply that arrives after the client gave up and before it sends the same request again
    is that request's answer: it is taken and the request is not sent a second time (a second
    copy would get a second answer, landing on the next request). Before, pymodbus threw it away
    and a device a little slower than the timeout looked silent on every attempt."""
    from pymodbus.framer import FramerType

    from drivers.transport.modbus import PatientSerialClient

    master, path = pty_pair
    os.set_blocking(master, False)
    client = PatientSerialClient(
        path, framer=FramerType.RTU, baudrate=115200, timeout=0.2, retries=0
    )
    assert client.connect()
    try:
        request = bytes([1, 3, 0, 8, 0, 2]) + crc16(bytes([1, 3, 0, 8, 0, 2]))
        client.send(request)
        assert _read_request(master, 8) == request
        assert client.recv(None) == b""  # the deadline passes
        body = bytes([1, 3, 4, 0x12, 0x34, 0x56, 0x78])
        os.write(master, body + crc16(body))  # the answer, late
        arrived(client, len(body) + 2)
        client.retrying = True
        client.send(request)  # the retry
        assert client.recv(None) == body + crc16(body)
        assert _read_request(master, 1, timeout_s=0.3) == b""  # not sent again
        # a different request never takes an earlier request's late bytes
        os.write(master, body + crc16(body))
        arrived(client, len(body) + 2)
        other = bytes([1, 3, 0, 0, 0, 4]) + crc16(bytes([1, 3, 0, 0, 0, 4]))
        client.send(other)
        assert _read_request(master, 8) == other
        assert client.recv(None) == b""
    finally:
        client.close()
