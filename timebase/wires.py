"""Clock-aware byte pipes: the wire between drivers and simulated devices in simulated time.

The bytes are the same as on a pseudo-terminal or a loopback socket; what changes is that waiting
for them is waiting on the simulated clock, and that a line with a baud rate delivers a write
``10 / baud`` s per byte after the line is free (8N1: start, 8 data, stop), as a UART does.

* Serial lines: the device side calls :meth:`Wires.serve_serial` (name, baud rate); a client opens
  ``simpipe://<name>`` with pyserial (:mod:`timebase.protocol_simpipe`), so drivers keep their own
  serial code. The device can see the speed the client set (``line.client_baud``).
* A loopback network: a server :meth:`~Wires.listen` s on a host and port, and every
  :meth:`~Wires.connect` gives it the server end of a new connection.

The names live on the simulated clock (``wires()``): a new clock starts with none.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

import serial

from timebase.clock import current
from timebase.sim_clock import Channel, NotOnTheClockError, SimulatedClock

if "timebase" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("timebase")  # simpipe:// (timebase.protocol_simpipe)

SCHEME = "simpipe://"
LOOPBACK = {"127.0.0.1", "localhost", "::1"}


class _Direction:
    """Bytes one way: each write arrives whole when its last byte has crossed the line."""

    def __init__(self, clock: SimulatedClock, baud: int | None, latency_s: float) -> None:
        self.clock = clock
        self.baud = baud
        self.latency_s = latency_s
        self.chunks: deque[tuple[float, bytes]] = deque()
        self.line_free_s = float("-inf")
        self.ch = Channel(clock)
        self.closed = False
        self.unread = 0  # bytes put and not yet read by the receiving end (in flight or arrived)

    def put(self, data: bytes) -> None:
        now = self.clock.monotonic()
        start = max(now, self.line_free_s)
        self.line_free_s = start + (len(data) * 10.0 / self.baud if self.baud else 0.0)
        arrival_s = self.line_free_s + self.latency_s
        self.chunks.append((arrival_s, bytes(data)))
        self.unread += len(data)
        self.clock.notify_at(arrival_s, self.ch)  # the reader wakes when it has arrived

    def arrived(self) -> bytes:
        now = self.clock.monotonic()
        out = b""
        while self.chunks and self.chunks[0][0] <= now:
            out += self.chunks.popleft()[1]
        return out

    def next_arrival_s(self) -> float | None:
        return self.chunks[0][0] if self.chunks else None


class PipeEnd:
    """One end of a duplex byte pipe (what a pty fd or a socket is to its holder)."""

    def __init__(self, name: str, rx: _Direction, tx: _Direction) -> None:
        self.name = name
        self._rx = rx
        self._tx = tx
        self._buf = bytearray()
        self.client_baud: int | None = None
        """The speed the client side configured (a serial line's termios, as a device sees it)."""
        self.opened = True
        """Someone holds this end open (a serial line's client end: between open and close)."""

    @property
    def peer_closed(self) -> bool:
        """The other end closed (a disconnect)."""
        return self._rx.closed

    @property
    def closed(self) -> bool:
        return self._tx.closed

    def close(self) -> None:
        """Close this end: the other end's reads return what is left, then nothing."""
        self.opened = False
        self._tx.closed = True
        self._tx.ch.notify()
        self._rx.ch.notify()

    def reopen(self) -> None:
        """Open again after :meth:`close` (a serial port opened anew): wakes the other end's
        :meth:`wait_peer_open`."""
        self.opened = True
        self._tx.closed = False
        self._tx.ch.notify()

    def wait_peer_open(self, timeout_s: float | None) -> bool:
        """Wait until the other end is open (True) or this end is closed or ``timeout_s`` passed
        (False; None: no limit)."""
        clock = self._rx.clock
        deadline = clock.deadline(timeout_s)
        while self._rx.closed and not self._tx.closed:
            if deadline is not None and clock.monotonic() >= deadline:
                return False
            clock.block((self._rx.ch,), deadline)
        return not self._rx.closed

    def write(self, data: bytes) -> int:
        """Send ``data``; BrokenPipeError when either end is closed."""
        if self._tx.closed or self._rx.closed:
            raise BrokenPipeError(f"{self.name}: the other end is gone")
        if data:
            self._tx.put(bytes(data))
        return len(data)

    def _collect(self) -> None:
        self._buf += self._rx.arrived()

    def _take(self, n: int) -> bytes:
        out = bytes(self._buf[:n])
        del self._buf[:n]
        self._rx.unread -= len(out)
        return out

    @property
    def in_waiting(self) -> int:
        """Bytes that have arrived and not been read."""
        self._collect()
        return len(self._buf)

    @property
    def out_waiting(self) -> int:
        """Bytes this end wrote that the other end has not read yet (on the line or arrived):
        what fills a receive buffer when nobody reads (a writer may drop data beyond it)."""
        return self._tx.unread

    def read_available(self, limit: int | None = None) -> bytes:
        """What has arrived (at most ``limit`` bytes), without waiting."""
        self._collect()
        return self._take(len(self._buf) if limit is None else min(limit, len(self._buf)))

    def _wait_for(self, count: int, timeout_s: float | None) -> bool:
        """Wait until ``count`` bytes have arrived or either end closed (True), or ``timeout_s``
        passed (False; None: no limit), waking when the next write in flight arrives."""
        clock = self._rx.clock
        deadline = clock.deadline(timeout_s)
        while True:
            self._collect()
            if len(self._buf) >= count or self._rx.closed or self._tx.closed:
                return True
            if deadline is not None and clock.monotonic() >= deadline:
                return False
            due = self._rx.next_arrival_s()
            wake = due if deadline is None else deadline if due is None else min(due, deadline)
            clock.block((self._rx.ch,), wake)

    def wait_readable(self, timeout_s: float | None) -> bool:
        """Wait until a byte has arrived or either end closed (True) or ``timeout_s`` passed."""
        return self._wait_for(1, timeout_s)

    def read(self, size: int, timeout_s: float | None) -> bytes:
        """Up to ``size`` bytes as pyserial reads: wait until there are ``size`` or ``timeout_s``
        passed (None: no limit; 0: what is there), or the peer closed."""
        self._wait_for(size, timeout_s)
        return self._take(size)

    def discard_input(self) -> None:
        """Throw away what has arrived."""
        self._collect()
        self._take(len(self._buf))


def pipe_pair(clock: SimulatedClock, name: str, baud: int | None = None,
              latency_s: float = 0.0) -> tuple[PipeEnd, PipeEnd]:  # fmt: skip
    """Two connected ends ``(a, b)``: what one writes the other reads."""
    ab = _Direction(clock, baud, latency_s)
    ba = _Direction(clock, baud, latency_s)
    return PipeEnd(name, ba, ab), PipeEnd(name, ab, ba)


class SerialLine:
    """A simulated serial line: ``device`` end for the simulated instrument, ``client`` end for
    whoever opens ``simpipe://<name>``."""

    def __init__(self, clock: SimulatedClock, name: str, baud: int | None) -> None:
        self.name = name
        self.device, self.client = pipe_pair(clock, name, baud)
        self.client.opened = False  # until a client opens simpipe://<name>

    @property
    def url(self) -> str:
        """What a client opens (pyserial URL)."""
        return SCHEME + self.name

    def set_baud(self, baud: int | None) -> None:
        """The line's speed from now on, both ways (a device switched its baud rate): later
        writes are paced at it (None: no pacing)."""
        self.device._tx.baud = self.device._rx.baud = baud


class Wires:
    """The serial lines and the loopback network of one simulated clock."""

    FIRST_PORT = 15020

    def __init__(self, clock: SimulatedClock) -> None:
        self.clock = clock
        self.lines: dict[str, SerialLine] = {}
        self.servers: dict[tuple[str, int], Callable[[PipeEnd], None]] = {}
        self._next_port = self.FIRST_PORT

    def serve_serial(self, name: str, baud: int | None = None) -> SerialLine:
        """A new serial line ``name`` (its device end is the caller's)."""
        if name in self.lines:
            raise ValueError(f"a simulated serial line '{name}' exists already")
        line = SerialLine(self.clock, name, baud)
        self.lines[name] = line
        return line

    def open_serial(self, name: str) -> PipeEnd:
        """The client end of line ``name`` (KeyError when there is none)."""
        end = self.lines[name].client
        end.reopen()
        return end

    def remove_serial(self, name: str) -> None:
        """The line is gone (a device unplugged): its client's next read or write fails."""
        line = self.lines.pop(name, None)
        if line is not None:
            line.device.close()

    def listen(self, host: str, port: int, accept: Callable[[PipeEnd], None]) -> int:
        """Accept connections to ``host:port`` (port 0: the next free one); returns the port.
        ``accept(end)`` gets the server end of each new connection."""
        key_host = _host(host)
        if port == 0:
            while (key_host, self._next_port) in self.servers:
                self._next_port += 1
            port = self._next_port
            self._next_port += 1
        if (key_host, port) in self.servers:
            raise OSError(f"simulated address {host}:{port} is in use")
        self.servers[(key_host, port)] = accept
        return port

    def unlisten(self, host: str, port: int) -> None:
        """Stop accepting connections at ``host:port``."""
        self.servers.pop((_host(host), port), None)

    def listening(self, host: str, port: int) -> bool:
        """Whether something accepts connections at ``host:port``."""
        return (_host(host), port) in self.servers

    def connect(self, host: str, port: int, latency_s: float = 0.0) -> PipeEnd:
        """A new connection to ``host:port`` (ConnectionRefusedError when nothing listens)."""
        accept = self.servers.get((_host(host), port))
        if accept is None:
            raise ConnectionRefusedError(f"nothing listens on simulated {host}:{port}")
        client, server = pipe_pair(self.clock, f"{host}:{port}", None, latency_s)
        accept(server)
        return client


def _host(host: str) -> str:
    return "127.0.0.1" if host in LOOPBACK else host


def wires() -> Wires:
    """The lines and network of the current simulated clock (NotOnTheClockError on the wall
    clock: the simulated wires exist only in simulated time)."""
    clock = current()
    if not isinstance(clock, SimulatedClock):
        raise NotOnTheClockError("simulated wires exist only on a simulated clock")
    found: Any = getattr(clock, "_wires", None)
    if found is None:
        found = Wires(clock)
        clock._wires = found  # type: ignore[attr-defined]
    return found  # type: ignore[no-any-return]
