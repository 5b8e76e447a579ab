"""A Modbus TCP device that is nothing but a register image: values typed in by a test from a
maker's or an independent client's table, never produced by the project's simulator.

Function 3 reads, 6 and 16 write (6 answers an echo of the request, 16 the address and count, as
the Modbus application protocol says); a register outside the image answers exception 2. Every
write is logged as (address, value) so a test sees the exact counts a driver sent.
"""

from __future__ import annotations

import socket
import socketserver
import struct
import threading
from collections.abc import Callable
from typing import Any


class RegisterImage:
    """Holding registers ``regs`` (address -> value) served on 127.0.0.1:``port``."""

    def __init__(
        self, regs: dict[int, int], on_write: Callable[[int, int], None] | None = None
    ) -> None:
        self.regs = dict(regs)
        self.writes: list[tuple[int, int]] = []
        self.on_write = on_write
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
        fc = pdu[0]
        if fc == 3:
            addr, count = struct.unpack(">HH", pdu[1:5])
            if any(a not in self.regs for a in range(addr, addr + count)):
                return bytes([0x83, 2])
            words = [self.regs[a] for a in range(addr, addr + count)]
            return bytes([3, 2 * count]) + struct.pack(f">{count}H", *words)
        if fc == 6:
            addr, value = struct.unpack(">HH", pdu[1:5])
            if addr not in self.regs:
                return bytes([0x86, 2])
            self._write(addr, value)
            return pdu[:5]
        if fc == 16:
            addr, count = struct.unpack(">HH", pdu[1:5])
            values = struct.unpack(f">{count}H", pdu[6 : 6 + 2 * count])
            if any(a not in self.regs for a in range(addr, addr + count)):
                return bytes([0x90, 2])
            for i, v in enumerate(values):
                self._write(addr + i, v)
            return pdu[:5]
        return bytes([fc | 0x80, 1])

    def _write(self, addr: int, value: int) -> None:
        self.regs[addr] = value
        self.writes.append((addr, value))
        if self.on_write is not None:
            self.on_write(addr, value)

    def close(self) -> None:
        """Stop serving."""
        self.server.shutdown()
        self.server.server_close()

    def __enter__(self) -> RegisterImage:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _recv(sock: socket.socket, n: int) -> bytes | None:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return buf
