"""How long this computer's terminal layer held serial data back: a canary on a private pty.

Linux hands received serial bytes to the reading process in a kernel worker thread (tty flip
buffers, flushed on an unbound workqueue), for pseudo-terminals and USB-serial adapters alike. On
a busy computer that worker can wait for a CPU for seconds: on this project's 2-core test machine
beside two CPU hogs, kernel workers waited up to 1.1 s to run 0.2 ms, and a pty round trip took
3.3 s while a socket round trip in the same minutes stayed under 0.1 s. A reply held back there
is late because of this computer, not because of the instrument, and must not be taken for a
dead device.

:class:`TtyWatch` measures it: a daemon thread writes one byte every :data:`PERIOD_S` into a pty
pair of its own and times its arrival. While a canary byte is overdue by more than
:data:`TOLERANCE_S`, the terminal layer counts as stalled. Serial timeouts add the stall inside
their window (:func:`tty_stall_s`), so a timeout measures the instrument. On an idle computer the
stall is 0 and every timeout is exactly what it says.

In simulated time (:mod:`timebase`, ADR 0038) there is no kernel terminal layer between a driver
and a simulated device (the bytes cross clock-aware pipes), and the intervals would be on another
clock: no canary is started and every stall is 0.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections import deque

import timebase

PERIOD_S = 0.02
"""Pause between canary bytes (s): a stall is noticed within this plus :data:`TOLERANCE_S`."""
TOLERANCE_S = 0.05
"""A canary byte later than this (s) marks the terminal layer as stalled beyond it."""
POLL_S = 0.01
"""How often the canary looks for its byte while it is late (s)."""
GAP_S = 0.02
"""A look that comes this much later than asked (s) was this process descheduled: the interval
before it is not counted, since the byte may have been there unseen."""
KEEP_S = 120.0
"""Stalls older than this (s) are forgotten: no serial wait is that long."""


class TtyWatch:
    """One canary pty and the stalls it saw, as monotonic intervals (s), in two measures:

    * **possible** (:meth:`stalled_s`): from :data:`TOLERANCE_S` after a byte was written until it
      was seen. It includes time the canary thread itself was not running (a busy process, the
      interpreter lock): generous, for timeouts, where waiting a little longer costs nothing;
    * **seen** (:meth:`seen_stalled_s`): only time the canary was looking, on time, and did not
      find its byte. For judging data: a busy process must not make its own samples suspect.
    """

    def __init__(self) -> None:
        self.pid = os.getpid()
        self._lock = threading.Lock()
        self._possible: deque[list[float]] = deque()  # [start, end], merged when adjacent
        self._seen: deque[list[float]] = deque()
        self._in_flight_since: float | None = None  # when the byte not yet seen was written
        self.worst_s = 0.0  # the longest canary delivery seen (s)
        self.running = False
        try:
            self._master, self._slave = os.openpty()
            tty.setraw(self._master)
            tty.setraw(self._slave)
        except OSError:
            return  # no ptys here: no serial stalls to account for
        self.running = True
        threading.Thread(target=self._run, name="tty-watch", daemon=True).start()

    def _note(self, spans: deque[list[float]], start: float, end: float) -> None:
        with self._lock:
            if spans and spans[-1][1] >= start - GAP_S:
                spans[-1][1] = max(spans[-1][1], end)
            else:
                spans.append([start, end])
            while spans and spans[0][1] < end - KEEP_S:
                spans.popleft()

    def _run(self) -> None:
        try:
            while True:
                sent = looked = time.monotonic()
                with self._lock:
                    self._in_flight_since = sent
                os.write(self._master, b"\0")
                while True:
                    ready = select.select([self._slave], [], [], POLL_S)[0]
                    now = time.monotonic()
                    on_time = now - looked <= POLL_S + GAP_S
                    if not ready and on_time and now - sent > TOLERANCE_S:
                        self._note(self._seen, max(looked, sent + TOLERANCE_S), now)
                    looked = now
                    if ready:
                        os.read(self._slave, 64)
                        self.worst_s = max(self.worst_s, now - sent)
                        if now - sent > TOLERANCE_S:
                            self._note(self._possible, sent + TOLERANCE_S, now)
                        with self._lock:
                            self._in_flight_since = None
                        break
                time.sleep(PERIOD_S)
        except (OSError, ValueError):
            self.running = False
            with self._lock:
                self._in_flight_since = None

    def stalled_s(self, since: float, until: float | None = None) -> float:
        """Seconds of ``[since, until]`` (monotonic; ``until`` default now) during which the
        terminal layer may have held data back (possible stalls, the one going on included)."""
        end = time.monotonic() if until is None else until
        with self._lock:
            spans = [(a, b) for a, b in self._possible]
            if self._in_flight_since is not None:
                spans.append((self._in_flight_since + TOLERANCE_S, end))
        return _overlap(spans, since, end)

    def seen_stalled_s(self, since: float, until: float | None = None) -> float:
        """Seconds of ``[since, until]`` during which the canary saw the terminal layer hold data
        back while it was itself running (at most :data:`POLL_S` behind)."""
        end = time.monotonic() if until is None else until
        with self._lock:
            spans = [(a, b) for a, b in self._seen]
        return _overlap(spans, since, end)


def _overlap(spans: list[tuple[float, float]], since: float, end: float) -> float:
    return sum(max(0.0, min(b, end) - max(a, since)) for a, b in spans)


_watch: TtyWatch | None = None
_watch_lock = threading.Lock()


def tty_watch() -> TtyWatch | None:
    """This process's canary, started on first use (and again in a forked child); None in
    simulated time, which has no terminal layer to watch."""
    global _watch
    if timebase.is_simulated():
        return None
    with _watch_lock:
        if _watch is None or _watch.pid != os.getpid():
            _watch = TtyWatch()
        return _watch


def _current() -> TtyWatch | None:
    """This process's canary if one was started (a forked child's copy is not its own); none in
    simulated time (its intervals are on the wall clock)."""
    if timebase.is_simulated():
        return None
    watch = _watch
    return watch if watch is not None and watch.pid == os.getpid() else None


def tty_stall_s(since: float, until: float | None = None) -> float:
    """Seconds of ``[since, until]`` (monotonic, s) the terminal layer may have held serial data
    back (generous: for timeouts); 0 before any serial port was opened in this process."""
    watch = _current()
    return 0.0 if watch is None else watch.stalled_s(since, until)


def tty_seen_stall_s(since: float, until: float | None = None) -> float:
    """Seconds of ``[since, until]`` the canary saw the terminal layer hold data back while this
    process was running (strict: for judging which samples came through a stall)."""
    watch = _current()
    return 0.0 if watch is None else watch.seen_stalled_s(since, until)
