"""A process that must act at once on a busy computer asks for a CPU before other work.

The guardian (:mod:`rig.engine.guardian`) is a safety watchdog: idle but for its 0.1 s looks, and
when the rig dies it must switch every output off now, not after the bench PC's other work. Linux
keeps the nice value per thread and a new thread inherits its creator's, so raising the main
thread's before any other starts raises the whole process.
"""

from __future__ import annotations

import os

GUARDIAN_NICE = -10
"""Nice value the guardian asks for (-20 highest .. 19 lowest) where the system allows it (root,
or ``CAP_SYS_NICE``): a safety watchdog asks for a CPU before other work, so a busy bench PC does
not hold the safe state back. It is idle but for its 0.1 s looks; its switch-off threads inherit
it. Elsewhere it runs at the rig's priority."""


def raise_own_priority(nice: int = GUARDIAN_NICE) -> bool:
    """The calling thread, and every thread it starts later, at ``nice``
    where allowed; whether it was."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, min(nice, os.getpriority(os.PRIO_PROCESS, 0)))
    except (OSError, AttributeError):  # EACCES/EPERM: not root and no CAP_SYS_NICE
        return False
    return True
