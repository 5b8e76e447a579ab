"""A simulated clock's threads on one CPU: handing the turn over there costs a tenth.

Exactly one participant of a simulated clock runs at a time, so a second CPU gains it nothing;
but a turn handed to a thread that sleeps on another CPU wakes it there through the kernel's
cross-CPU wake-up and the interpreter's lock, 41 us a hand-over on the 2-core machine against 4 us
with both threads on one CPU (ADR 0038). So :func:`one_cpu` confines the calling thread (and the
threads it starts, which inherit it) to the CPU it is running on when it enters, and gives back
its CPUs when it leaves. The kernel spreads running processes over the CPUs, so two simulations
at once (two test workers) usually start on two; each entry chooses again.

``TIMEBASE_CPU`` overrides the choice: a CPU number, or ``any`` to leave the threads wherever
the kernel puts them. Where the system cannot confine threads, nothing changes.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

ENV = "TIMEBASE_CPU"
"""The environment variable that chooses the CPU (a number) or leaves the choice (``any``)."""


def running_cpu() -> int | None:
    """The CPU the calling thread runs on now (Linux: field 39 of its ``stat``), else None."""
    try:
        stat = Path("/proc/thread-self/stat").read_text()
        return int(stat.rsplit(")", 1)[1].split()[36])
    except (OSError, IndexError, ValueError):
        return None


def chosen_cpu(allowed: set[int]) -> int | None:
    """The CPU to confine to, of ``allowed``: ``TIMEBASE_CPU``'s, else the running one (None:
    none, as asked, or none that is allowed, or only one allowed anyway)."""
    choice = os.environ.get(ENV, "").strip()
    if choice.lower() == "any" or len(allowed) < 2:
        return None
    cpu: int | None
    if choice:
        try:
            cpu = int(choice)
        except ValueError:
            raise ValueError(
                f"{ENV}={choice!r}: give a CPU number (one of {sorted(allowed)}) or 'any'"
            ) from None
    else:
        cpu = running_cpu()
    return cpu if cpu in allowed else None


@contextlib.contextmanager
def one_cpu() -> Iterator[int | None]:
    """Inside, the calling thread and the threads it starts run on one CPU (the one yielded;
    None: left as they were)."""
    if not hasattr(os, "sched_setaffinity"):
        yield None
        return
    before = os.sched_getaffinity(0)
    cpu = chosen_cpu(set(before))
    if cpu is None:
        yield None
        return
    os.sched_setaffinity(0, {cpu})
    try:
        yield cpu
    finally:
        os.sched_setaffinity(0, before)
