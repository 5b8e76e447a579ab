"""A busy computer on simulated time: the host's threads (the rig's and its drivers', never a
simulated instrument's) woken late, as a computer with more work than cores wakes them. Each time
a host thread could run again (its deadline came, or what it waited for happened) it runs only
after a random delay, drawn per thread from its own seeded stream: the same seed gives the same
delays on any machine, so what a loaded computer does to a run (late set-points, a sensor's
samples read in bursts, a timeout that measures us instead of the instrument) can be tried, and
tested, deterministically.

The instruments are not slowed: their threads and their wires keep simulated time exactly, as a
real instrument keeps its own; bytes they send wait in the host's buffers until a late reader
takes them.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass

INSTRUMENT_MODULES = ("sim", "timebase")
"""A thread whose target comes from one of these modules is an instrument's (or the clock's):
never late. Every other participant is the host's."""


@dataclass(frozen=True)
class BusyHost:
    """How late the host's threads run: each wake is late with probability ``share`` (0-1), by an
    exponentially distributed delay of mean ``mean_late_s`` (s), at most ``max_late_s`` (s)."""

    mean_late_s: float
    share: float = 1.0
    max_late_s: float = 2.0
    seed: int = 0

    def delays(self, thread_name: str) -> Callable[[], float]:
        """The delays (s) of one thread's wakes, from a stream of its own."""
        rng = random.Random(f"{self.seed}:{thread_name}")

        def draw() -> float:
            if rng.random() >= self.share:
                return 0.0
            return min(rng.expovariate(1.0 / self.mean_late_s), self.max_late_s)

        return draw


def is_host(target: object) -> bool:
    """Whether a thread running ``target`` is the host's (not an instrument's or the clock's)."""
    module = str(getattr(target, "__module__", "") or "")
    return module.split(".")[0] not in INSTRUMENT_MODULES
