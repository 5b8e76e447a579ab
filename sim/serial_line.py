"""The device end of a simulated serial line: what the HMR2300, the ASCII magnetometer and the
cesium counter write to and read from, whatever carries it.

* :class:`PtyLine` (the wall clock): a raw pseudo-terminal; the client opens its ``/dev/pts/N``.
* :class:`PipeLine` (simulated time, ADR 0038): a line of :func:`timebase.wires.wires`; the client
  opens ``simpipe://<name>`` with pyserial, and every wait is a wait on the simulated clock.

:func:`open_line` picks one by the clock current when the device starts. Both drop what does not
fit when the client does not read (a full receive buffer, as on a UART), report the speed the
client set (a device may ignore a client at the wrong speed) and never block on a write.
"""

from __future__ import annotations

import contextlib
import os
import random
import select
import termios
from typing import TYPE_CHECKING, Protocol

import timebase
from sim.physics import Faults
from sim.transports import Pty, damage, open_pty

if TYPE_CHECKING:
    import threading

SPEEDS = {
    getattr(termios, name): int(name[1:])
    for name in dir(termios)
    if name[:1] == "B" and name[1:].isdigit() and name != "B0"
}
"""termios speed constants to baud rates."""
LINE_BUFFER_BYTES = 20480
"""What a client's side holds unread before more is lost: what a Linux pseudo-terminal takes
before a non-blocking write fails (measured), so a simulated line loses the same."""


class SerialLine(Protocol):
    """The device's end of a serial line."""

    @property
    def has_client(self) -> bool:
        """Someone may be listening (a pty: always; a simulated line: a client has it open). A
        device may skip making what nobody can receive."""
        ...

    carries_line_time: bool
    """The line itself delays each write by its time on the wire (a simulated line); False: the
    client gets the bytes when they are written (a pty), so the device writes a frame when its
    last byte would have left, as a UART delivers it."""

    @property
    def path(self) -> str:
        """What the client opens (a device path, or a pyserial URL)."""
        ...

    def write(self, data: bytes) -> int:
        """Hand ``data`` to the line without waiting; returns how much was taken (less when the
        client's buffer is full: the rest is lost). OSError when the line is closed."""
        ...

    def wait_readable(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for bytes from the client (True: there are some).
        OSError or ValueError when the line is closed."""
        ...

    def read_available(self) -> bytes:
        """What the client sent and nobody read yet (b"" when nothing)."""
        ...

    def client_baud(self) -> int | None:
        """The speed the client configured (None: unknown)."""
        ...

    def set_baud(self, baud: int) -> None:
        """The device switched its own speed (what paces the line, not the client's setting)."""
        ...

    def close(self) -> None:
        """Close the device's end (idempotent)."""
        ...


class PtyLine:
    """A raw pseudo-terminal at ``baud`` (its termios speed: what a client reads back)."""

    carries_line_time = False
    has_client = True

    def __init__(self, baud: int) -> None:
        self.pty: Pty = open_pty()
        constant = getattr(termios, f"B{baud}", None)
        if constant is not None:  # what the client finds before it sets its own
            with contextlib.suppress(termios.error):
                attrs = termios.tcgetattr(self.pty.master)
                attrs[4] = attrs[5] = constant
                termios.tcsetattr(self.pty.master, termios.TCSANOW, attrs)

    @property
    def path(self) -> str:
        return self.pty.path

    def write(self, data: bytes) -> int:
        try:
            return os.write(self.pty.master, data)
        except BlockingIOError:
            return 0

    def wait_readable(self, timeout_s: float) -> bool:
        ready, _, _ = select.select([self.pty.master], [], [], max(0.0, timeout_s))
        return bool(ready)

    def read_available(self) -> bytes:
        try:
            return os.read(self.pty.master, 4096)
        except OSError:
            return b""

    def client_baud(self) -> int | None:
        """A pty carries no baud rate, but the client's termios speed is visible."""
        try:
            return SPEEDS.get(termios.tcgetattr(self.pty.slave)[5])
        except termios.error:
            return None

    def set_baud(self, baud: int) -> None:
        """Nothing: a pty has no speed of its own (its termios speed is the client's, which a
        device switching its speed must not change)."""

    def close(self) -> None:
        self.pty.close()


class PipeLine:
    """Line ``name`` of the current simulated clock at ``baud`` (``simpipe://<name>``): a write
    reaches the client when its last byte has crossed the line."""

    carries_line_time = True

    def __init__(self, name: str, baud: int) -> None:
        from timebase.wires import wires

        self._wires = wires()
        self.name = name
        self.line = self._wires.serve_serial(name, baud)
        self.end = self.line.device

    @property
    def path(self) -> str:
        return self.line.url

    @property
    def has_client(self) -> bool:
        return self.line.client.opened

    def write(self, data: bytes) -> int:
        end = self.end
        if end.closed:
            raise OSError(f"{self.name}: the line is closed")
        if end.peer_closed:
            return 0  # nobody has the port open: the bytes go nowhere
        room = max(0, LINE_BUFFER_BYTES - end.out_waiting)
        taken = bytes(data[:room])
        if taken:
            end.write(taken)
        return len(taken)

    def wait_readable(self, timeout_s: float) -> bool:
        end = self.end
        if end.closed:
            raise OSError(f"{self.name}: the line is closed")
        if end.peer_closed and not end.in_waiting:
            timebase.sleep(timeout_s)  # the client closed the port: nothing comes until it opens
            return bool(end.in_waiting)
        return end.wait_readable(max(0.0, timeout_s)) and bool(end.in_waiting)

    def read_available(self) -> bytes:
        return self.end.read_available()

    def client_baud(self) -> int | None:
        return self.line.client.client_baud

    def set_baud(self, baud: int) -> None:
        self.line.set_baud(baud)

    def close(self) -> None:
        if not self.end.closed:
            self._wires.remove_serial(self.name)


def open_line(name: str, baud: int) -> SerialLine:
    """The device end of a new line for device ``name``: a line of the simulated clock inside
    ``timebase.simulated()``, else a pseudo-terminal."""
    if timebase.is_simulated():
        return PipeLine(name, baud)
    return PtyLine(baud)


def send_paced(line: SerialLine, data: bytes, faults: Faults, rng: random.Random, baudrate: int,
               stop: threading.Event) -> bool:  # fmt: skip
    """Write ``data`` (damaged by ``faults``) to a device's line, after the time it takes on a
    UART at ``baudrate`` on a line that does not carry it (a pty; or until ``stop``, an event of
    the device's clock); False when it was lost (nobody reading and the buffer full, as on a
    UART)."""
    data = damage(data, faults, rng)
    line_s = len(data) * 10.0 / baudrate
    if not line.carries_line_time and stop.wait(line_s):
        return False  # stopped while the frame was on the wire
    try:
        if line.write(data) == 0 and data:
            return False
    except OSError:
        return False
    # a line that carries the line time delivers the frame line_s from now and queues what the
    # device writes meanwhile behind it: no wait here (one turn of the clock less per frame)
    return True
