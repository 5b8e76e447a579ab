"""A serial port opened by pyserial URL (device path, ``socket://``, ``rfc2217://``, ``loop://``,
and in simulated time ``simpipe://``, a line of :mod:`timebase.wires`).

Timeouts run on the process's clock (:mod:`timebase`): in simulated time a 0.5 s timeout is 0.5 s
of simulated time, and the compensations for a busy computer (this process descheduled, the
kernel's terminal layer holding bytes back) are nothing, as neither exists there."""

from __future__ import annotations

import serial

import timebase
from drivers.errors import DeviceNotFoundError, DeviceTimeoutError
from drivers.transport.tty_watch import tty_stall_s, tty_watch

OWN_STALL_TOLERANCE_S = 0.05
"""A wait that ends this much later than asked was this process being descheduled."""
DRAIN_LIMIT_S = 1.0
"""How long :meth:`SerialPort.drain_input` discards a line that keeps talking before it gives up
(a device streaming at its own rate never falls silent; before, the drain waited for ever)."""


def own_stall_s(elapsed_s: float, asked_s: float) -> float:
    """How much of a wait (s) was this process not running: the overshoot beyond ``asked_s``
    when it exceeds :data:`OWN_STALL_TOLERANCE_S`, else 0. Deadlines are extended by it, so a
    timeout measures the instrument, not the computer it shares. Always 0 in simulated time: a
    wait there ends exactly when asked."""
    if timebase.is_simulated():
        return 0.0
    over = elapsed_s - asked_s
    return over if over > OWN_STALL_TOLERANCE_S else 0.0


class SerialPort:
    """Byte-level access with timeouts that raise :class:`DeviceTimeoutError` naming the port.

    A timeout is the instrument's time: it is extended by time this process was descheduled and
    by time the kernel's terminal layer held received bytes back (:mod:`tty_watch`)."""

    def __init__(
        self, url: str, baudrate: int, *, timeout_s: float = 0.5, name: str = "serial"
    ) -> None:
        self.url = url
        self.name = name
        self.timeout_s = timeout_s
        self._rx = bytearray()  # received, not yet handed out
        tty_watch()
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s)
        except timebase.NotOnTheClockError:  # simpipe:// on the wall clock
            raise DeviceNotFoundError(
                f"{name}: cannot open {url}: a simulated line exists only in the simulated time"
                " of the process that serves it"
            ) from None
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceNotFoundError(
                f"{name}: cannot open {url}: {exc}; check the cable and the port name"
            ) from None

    @property
    def baudrate(self) -> int:
        """Current line speed."""
        return int(self._port.baudrate)

    @baudrate.setter
    def baudrate(self, value: int) -> None:
        self._port.baudrate = value

    def write(self, data: bytes) -> None:
        """Send bytes."""
        try:
            self._port.write(data)
            self._port.flush()
        except (serial.SerialException, OSError) as exc:
            raise DeviceNotFoundError(
                f"{self.name} on {self.url}: write failed ({exc}); is it still connected?"
            ) from None

    def _fill(self, timeout_s: float) -> float:
        """Move what has arrived into the receive buffer, waiting up to ``timeout_s`` (>= 0) for
        the first byte. One system call per chunk, not per byte: a thread that waits for the
        interpreter lock between reads must not turn a complete reply into a timeout."""
        t0 = timebase.monotonic()
        try:
            waiting = self._port.in_waiting
            if waiting:
                self._rx += self._port.read(waiting)
                return 0.0
            if timeout_s <= 0:
                return 0.0
            self._port.timeout = timeout_s
            first = self._port.read(1)
            if first:
                self._rx += first
                waiting = self._port.in_waiting
                if waiting:
                    self._rx += self._port.read(waiting)
        except (serial.SerialException, OSError) as exc:
            raise DeviceNotFoundError(
                f"{self.name} on {self.url}: read failed ({exc}); is it still connected?"
            ) from None
        return own_stall_s(timebase.monotonic() - t0, timeout_s)

    def _take(self, n: int) -> bytes:
        out = bytes(self._rx[:n])
        del self._rx[:n]
        return out

    def read_exact(self, n: int, timeout_s: float | None = None) -> bytes:
        """Exactly ``n`` bytes or :class:`DeviceTimeoutError`.

        The timeout measures the instrument: when it expires, whatever arrived meanwhile (while
        this process was descheduled, say) is still taken before the reply is declared missing.
        """
        limit_s = self.timeout_s if timeout_s is None else timeout_s
        start = timebase.monotonic()
        deadline = start + limit_s
        while len(self._rx) < n:
            remaining = deadline + tty_stall_s(start) - timebase.monotonic()
            deadline += self._fill(max(remaining, 0.0))
            if remaining <= 0:
                break
        if len(self._rx) < n:
            raise DeviceTimeoutError(
                f"{self.name} on {self.url}: got {len(self._rx)} of {n} bytes within"
                f" {limit_s:g} s; check power, cable and baud rate",
                bytes(self._rx),
            )
        return self._take(n)

    def read_until(
        self, terminator: bytes = b"\r", max_bytes: int = 256, timeout_s: float | None = None
    ) -> bytes:
        """Bytes up to and including ``terminator`` (or ``max_bytes`` without it), else
        :class:`DeviceTimeoutError`. Bytes after the terminator stay for the next read; like
        :meth:`read_exact`, a reply that is already there when the time is up is taken."""
        limit_s = self.timeout_s if timeout_s is None else timeout_s
        start = timebase.monotonic()
        deadline = start + limit_s
        while True:
            end = self._rx.find(terminator)
            if 0 <= end < max_bytes:
                return self._take(end + len(terminator))
            if len(self._rx) >= max_bytes:
                return self._take(max_bytes)
            remaining = deadline + tty_stall_s(start) - timebase.monotonic()
            before = len(self._rx)
            deadline += self._fill(max(remaining, 0.0))
            if remaining <= 0 and len(self._rx) == before:
                partial = bytes(self._rx[:max_bytes])
                raise DeviceTimeoutError(
                    f"{self.name} on {self.url}: no complete reply within {limit_s:g} s (got"
                    f" {partial!r}); check power, cable and baud rate",
                    partial,
                )

    def wait_readable(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for something to read (True at once when something has
        arrived already); False when nothing came. A wait on the port, not a polling loop."""
        if not self._rx:
            self._fill(max(timeout_s, 0.0))
        return bool(self._rx)

    def has_complete(self, terminator: bytes) -> bool:
        """A whole ``terminator``-ended reply has already arrived (does not wait)."""
        self._fill(0.0)
        return terminator in self._rx

    def in_waiting(self) -> int:
        """Bytes already received."""
        return len(self._rx) + int(self._port.in_waiting)

    def read_available(self) -> bytes:
        """Whatever has arrived, without waiting."""
        self._fill(0.0)
        return self._take(len(self._rx))

    def drain_input(self, quiet_s: float = 0.05) -> None:
        """Discard input until the line has been quiet for ``quiet_s`` (at most for
        :data:`DRAIN_LIMIT_S`, or 20 quiet times if longer: a line that never falls silent)."""
        self.wait_silent(quiet_s, max(DRAIN_LIMIT_S, 20.0 * quiet_s))

    def wait_silent(self, quiet_s: float, limit_s: float) -> bool:
        """Discard input until nothing has arrived for ``quiet_s`` (s): True then, False when
        bytes still come after ``limit_s`` (s). Both are the instrument's time: time the kernel's
        terminal layer may have held received bytes back (:mod:`tty_watch`) is not silence and
        does not count against the limit, and a quiet begins when the last byte was taken."""
        self._fill(0.0)  # what has arrived already goes, whatever the quiet asked for
        self._rx.clear()
        start = last = timebase.monotonic()
        while True:
            now = timebase.monotonic()
            silent_until = last + quiet_s + tty_stall_s(last, now)
            if now >= silent_until:
                return True
            limit = start + limit_s + tty_stall_s(start, now)
            if now >= limit:
                return False
            self._fill(min(silent_until, limit) - now)
            if self._rx:
                self._rx.clear()
                last = timebase.monotonic()

    def close(self) -> None:
        """Close the port."""
        self._port.close()
