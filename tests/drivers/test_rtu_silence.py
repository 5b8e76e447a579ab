"""The Modbus RTU line's silence (issue 53): before each request the driver keeps the line quiet
for t3.5, 3.5 characters of 11 bits (start, 8 data, parity or a second stop bit, stop) up to
19200 Bd and 1.75 ms above (Modbus over Serial Line V1.02, 2.5.1.1), counted from the last byte
of the previous reply or the end of its own previous request. Before, it sent as soon as
pymodbus had the reply: 0.10 ms was seen on a rig where 4.01 ms (9600 Bd) is due.

Measured two ways, 100 requests at 9600 and at 115200 Bd each:

* in simulated time (the main check): the simulated line carries each byte for 10 bits at the
  baud rate (timebase.wires), so the device sees when each request's first byte went onto the
  line and when its own reply's last byte left it, exactly, whatever the computer's load;
* on a pseudo-terminal, on the wall clock (real-time tier, docs/testing.md): the branch a real
  serial port takes (the driver sleeps instead of waiting on a simulated line). A pty carries no
  line time, so the device dates its reply before writing it and a request when it has read it:
  the gap it measures can only be longer than the one on the line, never shorter."""

from __future__ import annotations

import os
import select
import struct
import threading
import time
import tty

import pytest

import timebase
from drivers.transport.modbus import ModbusLink, rtu_silence_s
from tests.drivers.scripted import crc16
from timebase.wires import wires

pytestmark = pytest.mark.realtime

REQUESTS = 100
BAUDS = (9600, 115200)
SPEC_T35_S = {9600: 3.5 * 11 / 9600, 115200: 0.00175}  # 4.01 ms and the fixed 1.75 ms


def reply_to(request: bytes) -> bytes:
    """The answer to a read of holding registers: each register holds its address."""
    addr, count = struct.unpack(">HH", request[2:6])
    body = bytes([request[0], 3, 2 * count]) + b"".join(
        struct.pack(">H", addr + i) for i in range(count)
    )
    return body + crc16(body)


def test_t35_is_the_specifications() -> None:
    assert rtu_silence_s(9600) == pytest.approx(0.0040104, abs=1e-7)
    assert rtu_silence_s(19200) == pytest.approx(3.5 * 11 / 19200)
    assert rtu_silence_s(38400) == rtu_silence_s(115200) == 0.00175


@pytest.mark.parametrize("baud", BAUDS)
def test_the_line_is_silent_for_t35_before_each_request_in_simulated_time(baud: int) -> None:
    byte_s = 10.0 / baud  # what the simulated line carries: 8N1
    gaps: list[float] = []
    with timebase.simulated():
        end = wires().serve_serial("psu", baud=baud).device

        def device() -> None:
            reply_ended: float | None = None
            while end.wait_readable(None) and not end.peer_closed:
                request = end.read(8, 0.05)  # arrives whole when its last byte is in
                began = timebase.monotonic() - len(request) * byte_s
                if reply_ended is not None:
                    gaps.append(began - reply_ended)
                answer = reply_to(request)
                end.write(answer)  # the line is free: it starts now
                reply_ended = timebase.monotonic() + len(answer) * byte_s

        timebase.Thread(device, name="rtu-device", daemon=True).start()
        link = ModbusLink(name="psu", path="simpipe://psu", baudrate=baud, timeout_s=0.5)
        for i in range(REQUESTS):
            assert link.read_registers(i, 1) == [i]
        link.close()
    assert len(gaps) == REQUESTS - 1
    assert min(gaps) >= SPEC_T35_S[baud] - 1e-9, f"{min(gaps) * 1e3:.3f} ms"


@pytest.mark.parametrize("baud", BAUDS)
def test_the_line_is_silent_for_t35_before_each_request_on_a_pty(baud: int) -> None:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    gaps: list[float] = []

    def device() -> None:
        replied: float | None = None
        buf = b""
        while len(gaps) < REQUESTS - 1:
            if not select.select([master], [], [], 5.0)[0]:
                return
            buf += os.read(master, 64)
            seen = time.monotonic()  # no earlier than the request's last byte
            if len(buf) < 8:
                continue
            request, buf = buf[:8], buf[8:]
            if replied is not None:
                gaps.append(seen - replied)
            replied = time.monotonic()  # no later than the reply's first byte
            os.write(master, reply_to(request))

    thread = threading.Thread(target=device, daemon=True)
    thread.start()
    link = ModbusLink(name="psu", path=os.ttyname(slave), baudrate=baud, timeout_s=2.0)
    try:
        for i in range(REQUESTS):
            assert link.read_registers(i, 1) == [i]
    finally:
        link.close()
        thread.join(timeout=5.0)
        os.close(master)
        os.close(slave)
    assert len(gaps) == REQUESTS - 1
    assert min(gaps) >= SPEC_T35_S[baud], f"{min(gaps) * 1e3:.3f} ms"
