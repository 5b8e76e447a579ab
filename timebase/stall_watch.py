"""A wall-clock watch on a simulated clock: when no participant has been handed the turn for
``stall_s`` seconds of wall time, write what every participant waits for and every thread's
stack, once per stall (ADR 0038).

Simulated time moves only while its participants run; a participant blocked on something
outside the clock (a plain lock, a database's lock, a thread that is no participant) stops it
silently. This watch turns such a stall into a report that names the waiting."""

from __future__ import annotations

import faulthandler
import sys
import tempfile
import threading
import time
from typing import TextIO

from timebase.sim_clock import SimulatedClock

POLL_S = 1.0
"""How often the watch looks at the clock (wall seconds)."""


class StallWatch:
    """Watches ``clock`` from a daemon thread until :meth:`stop`; reports to ``out``."""

    def __init__(self, clock: SimulatedClock, stall_s: float, out: TextIO | None = None) -> None:
        if not stall_s > 0:
            raise ValueError(f"stall_s must be > 0 s, not {stall_s}")
        self.clock = clock
        self.stall_s = float(stall_s)
        self.out = out
        self.reports = 0
        """Stalls reported so far."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="sim-clock-watch", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        seen, since, reported = self.clock.switches, time.monotonic(), False
        while not self._stop.wait(min(POLL_S, self.stall_s)):
            switches = self.clock.switches
            now = time.monotonic()
            if switches != seen:
                seen, since, reported = switches, now, False
            elif not reported and now - since >= self.stall_s and self.clock.members():
                self._report(now - since)
                reported = True

    def _report(self, stalled_s: float) -> None:
        out = self.out if self.out is not None else sys.stderr
        self.reports += 1
        lines = [
            f"simulated clock stalled: no participant got the turn for {stalled_s:.1f} s of wall"
            f" time at simulated t = {self.clock.monotonic():.6f} s; participants:",
            *(f"  {line}" for line in self.clock.describe()),
            "a participant blocked outside the clock (a plain lock, a database, a thread that is"
            " no participant) stops simulated time; the stacks follow",
        ]
        print("\n".join(lines), file=out, flush=True)
        # faulthandler, never sys._current_frames(): on Python 3.11 a garbage collection inside
        # that call can deadlock the interpreter (CPython gh-106883; seen as a Dask worker hung
        # in its profiler); through a file of its own, as ``out`` may have no descriptor
        with tempfile.TemporaryFile(mode="w+") as stacks:
            faulthandler.dump_traceback(file=stacks, all_threads=True)
            stacks.seek(0)
            print(stacks.read(), file=out, flush=True)

    def stop(self) -> None:
        """End the watch (waits for its thread, at most one poll)."""
        self._stop.set()
        self._thread.join()
