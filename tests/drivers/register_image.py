"""A Modbus device that is nothing but a register image: values typed in by a test from a
maker's or an independent client's table, never produced by the project's simulator.

Function 3 reads, 6 and 16 write (6 answers an echo of the request, 16 the address and count, as
the Modbus application protocol says); with ``coils``, function 1 reads them and 5 writes one
(0xFF00 on, 0x0000 off; the reply an echo); an address outside the image answers exception 2,
any other function exception 1. Served on loopback Modbus TCP, and with :meth:`serve_rtu` as
Modbus RTU on a pseudo-terminal too. Every register write is logged as (address, value) so a test
sees the exact counts a driver sent, and every request, in order, as (function, address, values
or count)."""

from __future__ import annotations

import os
import select
import socket
import socketserver
import struct
import threading
import tty
from collections.abc import Callable
from typing import Any

from tests.drivers.scripted import crc16


class RegisterImage:
    """Holding registers ``regs`` (address -> value) and ``coils`` (address -> state) served on
    127.0.0.1:``port``; ``on_write(address, value)`` after each register write."""

    def __init__(
        self,
        regs: dict[int, int],
        on_write: Callable[[int, int], None] | None = None,
        coils: dict[int, bool] | None = None,
    ) -> None:
        self.regs = dict(regs)
        self.coils = dict(coils or {})
        self.writes: list[tuple[int, int]] = []
        self.requests: list[tuple[int, int, tuple[int, ...]]] = []
        self.on_write = on_write
        self._lock = threading.Lock()
        self._ptys: list[tuple[int, int]] = []
        self._rtu_threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        image = self

        class Handler(socketserver.BaseRequestHandler):
            def handle(self) -> None:
                sock: socket.socket = self.request
                while True:
                    head = _recv(sock, 7)
                    if head is None:
                        return
                    tid, _, length, unit = struct.unpack(">HHHB", head)
                    pdu = _recv(sock, length - 1)
                    if pdu is None:
                        return
                    reply = image.answer(pdu)
                    sock.sendall(struct.pack(">HHHB", tid, 0, len(reply) + 1, unit) + reply)

        self.server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.port: int = self.server.server_address[1]
        self._thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self._thread.start()

    def answer(self, pdu: bytes) -> bytes:
        """The reply PDU to a request PDU."""
        with self._lock:
            return self._answer(pdu)

    def _answer(self, pdu: bytes) -> bytes:
        fc = pdu[0]
        addr, count = struct.unpack(">HH", pdu[1:5])
        if fc == 16:
            values = struct.unpack(f">{count}H", pdu[6 : 6 + 2 * count])
            self.requests.append((fc, addr, values))
        else:
            self.requests.append((fc, addr, (count,)))
        if fc in (1, 5):
            return self._coil(fc, addr, count, pdu)
        if fc == 3:
            if any(a not in self.regs for a in range(addr, addr + count)):
                return bytes([0x83, 2])
            words = [self.regs[a] for a in range(addr, addr + count)]
            return bytes([3, 2 * count]) + struct.pack(f">{count}H", *words)
        if fc == 6:
            if addr not in self.regs:
                return bytes([0x86, 2])
            self._write(addr, count)
            return pdu[:5]
        if fc == 16:
            if any(a not in self.regs for a in range(addr, addr + count)):
                return bytes([0x90, 2])
            for i, v in enumerate(values):
                self._write(addr + i, v)
            return pdu[:5]
        return bytes([fc | 0x80, 1])

    def _coil(self, fc: int, addr: int, count: int, pdu: bytes) -> bytes:
        """Function 1 (``count`` coils, packed bit 0 first) or 5 (``count`` is the value)."""
        if fc == 5:
            if addr not in self.coils:
                return bytes([0x85, 2])
            if count not in (0xFF00, 0x0000):
                return bytes([0x85, 3])
            self.coils[addr] = count == 0xFF00
            return pdu[:5]
        if any(a not in self.coils for a in range(addr, addr + count)):
            return bytes([0x81, 2])
        data = bytearray((count + 7) // 8)
        for i in range(count):
            if self.coils[addr + i]:
                data[i // 8] |= 1 << (i % 8)
        return bytes([1, len(data)]) + bytes(data)

    def _write(self, addr: int, value: int) -> None:
        self.regs[addr] = value
        self.writes.append((addr, value))
        if self.on_write is not None:
            self.on_write(addr, value)

    def serve_rtu(self, unit: int = 1) -> str:
        """The same image as Modbus RTU device ``unit`` on a pseudo-terminal; returns the path a
        driver opens. Requests for another unit, and bytes that frame no request (a text probe,
        a bad CRC), get no reply, as on an RS-485 line."""
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        self._ptys.append((master, slave))
        thread = threading.Thread(target=self._rtu, args=(master, unit), daemon=True)
        self._rtu_threads.append(thread)
        thread.start()
        return os.ttyname(slave)

    def _rtu(self, master: int, unit: int) -> None:
        buf = b""
        while not self._stopping.is_set():
            try:
                ready, _, _ = select.select([master], [], [], 0.05)
                if not ready:
                    buf = b""  # a silence ends any frame (a partial one is dropped)
                    continue
                buf += os.read(master, 256)
            except OSError:  # closed
                return
            while (n := _rtu_length(buf)) and len(buf) >= n:
                frame, buf = buf[:n], buf[n:]
                if frame[0] != unit or crc16(frame[:-2]) != frame[-2:]:
                    continue
                reply = bytes([unit]) + self.answer(frame[1:-2])
                os.write(master, reply + crc16(reply))
            if _rtu_length(buf) is None:
                buf = b""

    def close(self) -> None:
        """Stop serving."""
        self.server.shutdown()
        self.server.server_close()
        # the RTU threads end before their descriptors close: a thread still reading a closed
        # descriptor's number would serve the next image's pty, which reuses it (seen: a scan
        # found the previous test's model code)
        self._stopping.set()
        for thread in self._rtu_threads:
            thread.join(timeout=5.0)
        self._rtu_threads.clear()
        for master, slave in self._ptys:
            os.close(master)
            os.close(slave)
        self._ptys.clear()

    def __enter__(self) -> RegisterImage:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _rtu_length(buf: bytes) -> int | None:
    """Length of the RTU request ``buf`` starts (CRC included); 0 while its header is incomplete;
    None for a function this image does not frame."""
    if len(buf) < 2:
        return 0
    if buf[1] in (1, 3, 5, 6):
        return 8
    if buf[1] == 16:
        return 9 + buf[6] if len(buf) >= 7 else 0
    return None


def _recv(sock: socket.socket, n: int) -> bytes | None:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return buf
