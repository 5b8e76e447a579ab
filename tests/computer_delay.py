"""What this computer, not the product, spent of a wall-clock interval: for the real-time tier's
time-to-safe bounds (ADR 0038).

From its start: the longest wait for a CPU of any thread of each watched process (this one, which
hosts the simulated cage, and the product's processes that act), added, and the time the kernel's
terminal layer was seen holding serial data (:mod:`drivers.transport.tty_watch`). Idle it is about
0 and a bound of 1 s is judged as it stands; beside CPU hogs the bound is judged on the rest. A
process that has ended counts with what was noted of it before.
"""

from __future__ import annotations

import time

from drivers.transport.tty_watch import tty_seen_stall_s, tty_watch
from rig.engine.cpu_wait import CpuWaitLog


class ComputerDelay:
    """Started at construction; :meth:`seconds` is the computer's share so far (s)."""

    def __init__(self, *pids: int) -> None:
        tty_watch()  # the canary (usually started earlier, before a serial link was opened)
        self.t0 = time.monotonic()
        self.logs = [CpuWaitLog(pid=p) for p in ("self", *pids)]
        for log in self.logs:
            log.note(self.t0)

    def cpu_s(self) -> float:
        """The watched processes' CPU waits since the start (s): the longest thread of each,
        added."""
        now = time.monotonic()
        for log in self.logs:
            log.note(now)
        return sum(log.waited_since(self.t0) for log in self.logs)

    def seconds(self) -> float:
        """:meth:`cpu_s` and the terminal layer's seen stall since the start (s)."""
        cpu_s = self.cpu_s()
        return cpu_s + tty_seen_stall_s(self.t0, time.monotonic())
