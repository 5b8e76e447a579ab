"""Tiny devices on simulated wires (timebase.wires), for driving the real drivers in simulated
time: a Modbus RTU server on a serial line, a Modbus TCP server on the loopback network, a line
echo, and CPU hogs to run beside them. Each device is a participant of the clock
(timebase.Thread) and ends when its client closes its end."""

from __future__ import annotations

import struct
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import timebase
from tests.drivers.scripted import crc16
from timebase.wires import PipeEnd, wires


class Registers:
    """A holding-register image and what its server saw."""

    def __init__(self, values: dict[int, int] | None = None, *, silent: bool = False,
                 delay_s: float = 0.0, derive: Callable[[dict[int, int]], None] | None = None
                 ) -> None:  # fmt: skip
        self.values = dict(values or {})
        self.silent = silent
        self.delay_s = delay_s
        self.derive = derive
        """Called with the registers after every write (read-backs that follow set-points)."""
        self.requests: list[tuple[float, bytes]] = []

    def answer(self, pdu: bytes) -> bytes:
        """The reply PDU to a request PDU (functions 3 and 6)."""
        fc = pdu[0]
        if fc == 3:
            addr, count = struct.unpack(">HH", pdu[1:5])
            data = b"".join(struct.pack(">H", self.values.get(addr + i, 0)) for i in range(count))
            return bytes([3, len(data)]) + data
        if fc == 6:
            addr, value = struct.unpack(">HH", pdu[1:5])
            self.values[addr] = value
        elif fc == 16:
            addr, count = struct.unpack(">HH", pdu[1:5])
            for i in range(count):
                self.values[addr + i] = struct.unpack(">H", pdu[6 + 2 * i : 8 + 2 * i])[0]
        else:
            return bytes([fc | 0x80, 1])
        if self.derive is not None:
            self.derive(self.values)
        return pdu[:5]


def serve_rtu(name: str, regs: Registers, *, baud: int = 115200, unit: int = 1) -> None:
    """A Modbus RTU server on serial line ``name`` (requests of 8 bytes: functions 3 and 6)."""
    line = wires().serve_serial(name, baud=baud)
    end = line.device

    def run() -> None:
        while end.wait_readable(None) and not end.peer_closed:
            request = end.read(8, 0.05)
            regs.requests.append((timebase.monotonic(), request))
            if regs.silent or len(request) < 8 or request[0] != unit:
                continue
            timebase.sleep(regs.delay_s)
            reply = bytes([unit]) + regs.answer(request[1:6])
            end.write(reply + crc16(reply))

    timebase.Thread(run, name=f"rtu-{name}", daemon=True).start()


def serve_tcp(regs: Registers, *, host: str = "127.0.0.1", port: int = 0) -> int:
    """A Modbus TCP server on the simulated loopback network; returns its port."""

    def accept(end: PipeEnd) -> None:
        def run() -> None:
            while end.wait_readable(None) and not end.peer_closed:
                head = end.read(7, 0.05)
                if len(head) < 7:
                    continue
                tid, _, length, unit = struct.unpack(">HHHB", head)
                pdu = end.read(length - 1, 0.05)
                regs.requests.append((timebase.monotonic(), head + pdu))
                if regs.silent:
                    continue
                timebase.sleep(regs.delay_s)
                reply = regs.answer(pdu)
                end.write(struct.pack(">HHHB", tid, 0, len(reply) + 1, unit) + reply)

        timebase.Thread(run, name="modbus-tcp-connection", daemon=True).start()

    return wires().listen(host, port, accept)


def serve_echo(name: str, *, baud: int = 9600, silent: bool = False) -> None:
    """A line device on ``name``: answers each ``\\r``-ended line with it upper-cased (or not)."""
    end = wires().serve_serial(name, baud=baud).device

    def run() -> None:
        got = b""
        while end.wait_readable(None) and not end.peer_closed:
            got += end.read_available()
            while b"\r" in got:
                line, got = got.split(b"\r", 1)
                if not silent:
                    end.write(line.upper() + b"\r")

    timebase.Thread(run, name=f"echo-{name}", daemon=True).start()


@contextmanager
def cpu_hogs(n: int = 2) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``n`` processes that keep a CPU busy for as long as the block lasts."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield hogs
    finally:
        for hog in hogs:
            hog.kill()
        for hog in hogs:
            hog.wait()
