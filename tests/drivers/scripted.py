"""Scripted peers on real transports: they expect exact request bytes and send exact replies.

A peer records any mismatch and answers nothing to an unexpected request, so a driver that sends
the wrong bytes fails with its own timeout error and the test reports the mismatch.
"""

from __future__ import annotations

import os
import select
import socket
import struct
import threading
import time
import tty
from dataclasses import dataclass, field


def crc16(data: bytes) -> bytes:
    """Modbus RTU CRC (polynomial 0xA001, little-endian on the wire); written out independently."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return struct.pack("<H", crc)


def rtu(frame_hex: str) -> bytes:
    """An RTU frame from hex (without CRC); the CRC is appended."""
    body = bytes.fromhex(frame_hex)
    return body + crc16(body)


@dataclass
class Exchange:
    """Expect ``request`` (b"" = send without waiting), then send ``reply``."""

    request: bytes
    reply: bytes
    delay_s: float = 0.0  # wait before replying (e.g. until the driver has opened the port)


@dataclass
class ScriptedSerialPeer:
    """The device end of a pty running a script; ``path`` is what the driver opens."""

    script: list[Exchange]
    mismatches: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tty.setraw(self.master)
        self.path = os.ttyname(self.slave)
        self.done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _read_exact(self, n: int, timeout_s: float = 3.0) -> bytes:
        buf = b""
        while len(buf) < n:
            ready, _, _ = select.select([self.master], [], [], timeout_s)
            if not ready:
                break
            buf += os.read(self.master, n - len(buf))
        return buf

    def _run(self) -> None:
        for step in self.script:
            if step.request:
                got = self._read_exact(len(step.request))
                if got != step.request:
                    self.mismatches.append(f"expected {step.request.hex(' ')}, got {got.hex(' ')}")
                    break
            if step.delay_s:
                time.sleep(step.delay_s)
            if step.reply:
                os.write(self.master, step.reply)
        self.done.set()

    def close(self) -> None:
        self.done.wait(5)
        os.close(self.master)
        os.close(self.slave)


@dataclass
class ScriptedTcpPeer:
    """A Modbus TCP device: checks each request PDU (unit id onwards), echoes the transaction id."""

    script: list[tuple[bytes, bytes]]  # (request unit+PDU, reply unit+PDU)
    mismatches: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        conn, _ = self.server.accept()
        with conn:
            conn.settimeout(3.0)
            for request, reply in self.script:
                try:
                    header = conn.recv(7, socket.MSG_WAITALL)
                    tid, _proto, length, unit = struct.unpack(">HHHB", header)
                    pdu = conn.recv(length - 1, socket.MSG_WAITALL)
                except (TimeoutError, struct.error):
                    self.mismatches.append("no request")
                    return
                got = bytes([unit]) + pdu
                if got != request:
                    self.mismatches.append(f"expected {request.hex(' ')}, got {got.hex(' ')}")
                    return
                if reply:
                    conn.sendall(struct.pack(">HHH", tid, 0, len(reply)) + reply)

    def close(self) -> None:
        self._thread.join(timeout=5)
        self.server.close()


@dataclass
class ScriptedI2CBus:
    """An ``i2c_rdwr`` object: each call must match the next expected transfer."""

    script: list[tuple[int, bytes, int, bytes]]  # (address, written bytes, read length, read bytes)
    nack_addresses: set[int] = field(default_factory=set)
    mismatches: list[str] = field(default_factory=list)

    def i2c_rdwr(self, *msgs: object) -> None:
        import ctypes

        addr = int(msgs[0].addr)  # type: ignore[attr-defined]
        if addr in self.nack_addresses:
            raise OSError(121, "Remote I/O error")
        written = b"".join(ctypes.string_at(m.buf, m.len) for m in msgs if not m.flags & 1)  # type: ignore[attr-defined]
        reads = [m for m in msgs if m.flags & 1]  # type: ignore[attr-defined]
        if not self.script:
            self.mismatches.append(f"unexpected transfer {written.hex(' ')}")
            raise OSError(121, "script exhausted")
        e_addr, e_written, e_len, data = self.script.pop(0)
        if (addr, written, sum(int(m.len) for m in reads)) != (e_addr, e_written, e_len):  # type: ignore[attr-defined]
            self.mismatches.append(
                f"expected {e_addr:#x} {e_written.hex(' ')} read {e_len}, got {addr:#x} {written.hex(' ')}"
            )
            raise OSError(121, "unexpected transfer")
        for m in reads:
            ctypes.memmove(m.buf, data, int(m.len))  # type: ignore[attr-defined]
