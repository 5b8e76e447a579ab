"""Threads' nice values as the kernel reports them (for the instrument-priority tests)."""

from __future__ import annotations


def nice_of(tid: int, pid: int | str = "self") -> int:
    """The nice value of thread ``tid`` of process ``pid`` (field 19 of its ``stat``)."""
    with open(f"/proc/{pid}/task/{tid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[16])
