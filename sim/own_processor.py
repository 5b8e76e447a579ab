"""The simulated instruments ask for a CPU before other work, as real ones have their own processors.

A real magnetometer streams and a real supply answers whatever the bench PC is doing; a simulated
one shares the PC's cores with the rig, the tests, a browser and whatever else runs there. On the
wall clock, a simulator thread kept waiting for a CPU for two seconds is an instrument silent for
two seconds, and the rig rightly calls that a stalled sensor (seen beside two CPU hogs: "dut: no
data for 2.7 s"). The rig discounts its own waits for a CPU (``rig.engine.cpu_wait``); it cannot see
another process's. So the simulator's threads run at a raised priority (a lower nice value) where
the system allows it (root, or ``CAP_SYS_NICE``); elsewhere they run as before.

Linux keeps the nice value per thread and a new thread inherits its creator's, so
:func:`instrument_priority` raises the calling thread's, starts the devices (their threads inherit
it), and puts the caller's back. Nothing happens on simulated time: no participant waits for a CPU
there.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import timebase

INSTRUMENT_NICE = -10
"""Nice value of the simulated instruments' threads (-20 highest .. 19 lowest): about nine times
the CPU share of an ordinary thread (nice 0) while they are runnable, which they seldom are."""


@contextlib.contextmanager
def instrument_priority(nice: int = INSTRUMENT_NICE) -> Iterator[bool]:
    """Threads started inside run at nice value ``nice``; yields whether the system allowed it.
    The calling thread's own nice value is restored on exit (raising it back is always allowed)."""
    if timebase.is_simulated() or not hasattr(os, "setpriority"):
        yield False
        return
    tid = 0  # "the calling thread" for PRIO_PROCESS on Linux
    before = os.getpriority(os.PRIO_PROCESS, tid)
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(nice, before))
        raised = True
    except OSError:  # EACCES/EPERM: not root and no CAP_SYS_NICE
        raised = False
    try:
        yield raised
    finally:
        if raised:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, tid, before)
