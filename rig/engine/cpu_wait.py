"""Time this process's threads waited, runnable, for a CPU (Linux schedstat).

On a busy computer (CI and bench PCs share their cores) a thread can be ready and still not run
for a second or more. A check that judges an instrument by how long it went quiet ("no data for
1.5 s") must not count that time against the instrument: its data sat in a buffer while we were
not running. The sampler thread itself, or whichever thread held the interpreter lock it needed,
may have been the one kept waiting, so the largest wait of any thread is what is discounted.
"""

from __future__ import annotations

import os
import threading
from collections import deque


def run_delay_s(tid: int | None, pid: int | str = "self") -> float:
    """Total time (s) thread ``tid`` of process ``pid`` (default this one) has waited, runnable,
    for a CPU (Linux schedstat); 0 where the kernel does not say."""
    try:
        with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
            return int(f.read().split()[1]) / 1e9
    except (OSError, ValueError, IndexError):
        return 0.0


def thread_delays_s(pid: int | str = "self") -> dict[int, float]:
    """:func:`run_delay_s` of every thread of process ``pid`` (default this one), by thread id."""
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        return {}
    return {tid: run_delay_s(tid, pid) for tid in tids}


class CpuWaitLog:
    """Snapshots of every thread's CPU wait (of this process, or of ``pid``: the fault harness
    watches a rig it is about to kill), taken by :meth:`note` (call it every check round);
    :meth:`waited_since` tells how long the most delayed thread waited since a moment."""

    def __init__(self, keep: int = 2000, pid: int | str = "self") -> None:
        self._snapshots: deque[tuple[float, dict[int, float]]] = deque(maxlen=keep)
        self.pid = pid

    def note(self, now: float) -> None:
        """Record every thread's wait so far at monotonic time ``now`` (s)."""
        self._snapshots.append((now, thread_delays_s(self.pid)))

    def waited_since(self, since: float) -> float:
        """Largest CPU wait (s) of any thread from the last snapshot at or before ``since``
        (the oldest one if none is that old) to the newest; 0 without two snapshots. A thread
        born after that snapshot counts with all of its wait."""
        if len(self._snapshots) < 2:
            return 0.0
        base = self._snapshots[0][1]
        for t, delays in self._snapshots:
            if t > since:
                break
            base = delays
        newest = self._snapshots[-1][1]
        return max((newest[tid] - base.get(tid, 0.0) for tid in newest), default=0.0)


class ReadWaits:
    """How long a reading thread waits for a CPU while its data sit in a buffer: each read's
    run-queue wait (the thread's schedstat across the read) and their median over the last
    :data:`READ_WAITS` reads. A stream whose every arrival we read at least this late has dates
    that late too (its clock's lower envelope cannot see a delay common to all its arrivals), so
    it widens their uncertainty. Nothing on simulated time (a participant never waits for a CPU
    there) or where the kernel does not say."""

    def __init__(self, measure: bool) -> None:
        """Made by the reading thread itself (its thread id is the one measured)."""
        self.measure = measure
        self._waits: deque[float] = deque(maxlen=READ_WAITS)
        self._tid = threading.get_native_id()
        self._before = 0.0

    def start(self) -> None:
        """Before a read (from the reading thread)."""
        if self.measure:
            self._before = run_delay_s(self._tid)

    def typical_s(self) -> float:
        """After the read: the median run-queue wait (s) of the recent reads, this one counted."""
        if not self.measure:
            return 0.0
        self._waits.append(max(0.0, run_delay_s(self._tid) - self._before))
        ordered = sorted(self._waits)
        return ordered[len(ordered) // 2]


READ_WAITS = 50
"""Reads the typical wait is taken over."""
