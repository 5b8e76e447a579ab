"""A simulated clock's threads on one CPU: handing the turn over there costs a tenth.

Exactly one participant of a simulated clock runs at a time, so a second CPU gains it nothing;
but a turn handed to a thread that sleeps on another CPU wakes it there through the kernel's
cross-CPU wake-up and the interpreter's lock, 41 us a hand-over on the 2-core machine against 4 us
with both threads on one CPU (ADR 0038). So :func:`one_cpu` confines the calling thread (and the
threads it starts, which inherit it) to the CPU it is running on when it enters, and gives back
its CPUs when it leaves. Two simulations at once (two test workers, two Dask workers) take
different CPUs while there are free ones: each claims its CPU with a lock file
(``<temp>/timebase-cpus-<uid>/cpu<N>.lock``, released when it leaves or its process dies) and
takes the next unclaimed one when the one it runs on is claimed.

``TIMEBASE_CPU`` overrides the choice: a CPU number, or ``any`` to leave the threads wherever
the kernel puts them. Where the system cannot confine threads, nothing changes.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
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
    with contextlib.ExitStack() as claims:
        if not os.environ.get(ENV, "").strip():  # chosen here, not by the user: claim one
            cpu = _claim(cpu, sorted(before), claims)
        os.sched_setaffinity(0, {cpu})
        try:
            yield cpu
        finally:
            os.sched_setaffinity(0, before)


def _claim(preferred: int, allowed: list[int], claims: contextlib.ExitStack) -> int:
    """Claim ``preferred`` or else the first unclaimed CPU of ``allowed`` (its lock file held
    until ``claims`` closes); ``preferred`` unclaimed when every one is claimed."""
    folder = Path(tempfile.gettempdir()) / f"timebase-cpus-{os.getuid()}"
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
    except OSError:
        return preferred
    for cpu in [preferred, *(c for c in allowed if c != preferred)]:
        try:
            fd = os.open(folder / f"cpu{cpu}.lock", os.O_RDWR | os.O_CREAT, 0o600)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        claims.callback(os.close, fd)  # closing the file releases the claim
        return cpu
    return preferred
