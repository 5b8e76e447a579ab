"""The links to an external flight computer, one per address scheme (:data:`LINKS`):

* ``udp://HOST:PORT``: one space packet per datagram;
* ``serial:///dev/PORT?baud=N`` (default 115200 baud): a byte stream, so each packet follows the
  CCSDS attached sync marker ``1A CF FC 1D`` (CCSDS 131.0-B); the receiver hunts for the marker,
  so bytes lost or garbled on the line cost the packets they touch, never the packets after.

Timeouts are wall-clock: the flight computer is another machine, whatever clock the run is on.
"""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass
from typing import Protocol
from urllib.parse import parse_qs, urlsplit

from rig.errors import UserInputError
from rig.hil.packets import HEADER

SYNC_MARKER = bytes.fromhex("1ACFFC1D")
"""The CCSDS attached sync marker before each packet on a serial line."""
DEFAULT_BAUD = 115200
MAX_DATA = 1024
"""The longest packet data this protocol sends (bytes): a marker followed by a longer length is
a false one, in garbage, and the hunt goes on past it."""
FORMS = "udp://HOST:PORT or serial:///dev/PORT[?baud=N]"


class Link(Protocol):
    """Packets to and from the flight computer."""

    def send(self, packet: bytes) -> None: ...

    def receive(self, deadline_s: float) -> bytes | None:
        """The next packet's bytes, or None at ``deadline_s`` (time.monotonic s)."""
        ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Address:
    """A parsed flight-computer address: its scheme and where (host and port, or a device path
    and its baud rate)."""

    scheme: str
    target: str
    number: int

    def open(self) -> Link:
        return UdpLink(self) if self.scheme == "udp" else SerialLink(self)


def parse_address(text: str) -> Address:
    """``udp://HOST:PORT`` or ``serial:///dev/PORT[?baud=N]``; UserInputError naming the forms."""
    parts = urlsplit(text)
    if parts.scheme == "udp" and parts.hostname and parts.port is not None:
        return Address("udp", parts.hostname, parts.port)
    if parts.scheme == "serial" and parts.path.startswith("/") and not parts.netloc:
        query = parse_qs(parts.query)
        unknown = sorted(set(query) - {"baud"})
        baud = query.get("baud", [str(DEFAULT_BAUD)])[-1]
        if not unknown and baud.isdigit() and int(baud) > 0:
            return Address("serial", parts.path, int(baud))
    raise UserInputError(f"flight computer {text!r}: give it as {FORMS}")


class UdpLink:
    """One packet per datagram."""

    def __init__(self, address: Address) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect((address.target, address.number))

    def send(self, packet: bytes) -> None:
        self.sock.send(packet)

    def receive(self, deadline_s: float) -> bytes | None:
        left = deadline_s - time.monotonic()
        if left <= 0:
            return None
        self.sock.settimeout(left)
        try:
            return self.sock.recv(2048)
        except TimeoutError:
            return None

    def close(self) -> None:
        self.sock.close()


class SerialLink:
    """Each packet after the sync marker on a serial line (pyserial: a device path or a pty)."""

    def __init__(self, address: Address) -> None:
        import serial

        try:
            self.port = serial.Serial(address.target, baudrate=address.number, timeout=0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise UserInputError(
                f"flight computer serial://{address.target}: cannot open it ({exc}); check the"
                " cable and the port name"
            ) from None
        self.buffer = bytearray()
        self.skipped = 0  # bytes passed over while hunting for a marker

    def send(self, packet: bytes) -> None:
        self.port.write(SYNC_MARKER + packet)
        self.port.flush()

    def receive(self, deadline_s: float) -> bytes | None:
        while True:
            packet = self._packet()
            if packet is not None:
                return packet
            left = deadline_s - time.monotonic()
            if left <= 0:
                return None
            self.port.timeout = left
            chunk = self.port.read(max(1, self.port.in_waiting))
            self.buffer += chunk

    def _packet(self) -> bytes | None:
        """A whole packet from the buffer, or None (the buffer keeps what may start one)."""
        start = len(SYNC_MARKER)
        while True:
            at = self.buffer.find(SYNC_MARKER)
            if at < 0:
                drop = max(0, len(self.buffer) - (start - 1))  # a marker may be arriving split
                self.skipped += drop
                del self.buffer[:drop]
                return None
            self.skipped += at
            del self.buffer[:at]
            if len(self.buffer) < start + HEADER.size:
                return None
            length = HEADER.unpack_from(self.buffer, start)[2] + 1
            if length <= MAX_DATA:
                break
            self.skipped += 1  # a false marker: hunt on past its first byte
            del self.buffer[:1]
        end = start + HEADER.size + length
        if len(self.buffer) < end:
            return None
        packet = bytes(self.buffer[start:end])
        del self.buffer[:end]
        return packet

    def close(self) -> None:
        self.port.close()
