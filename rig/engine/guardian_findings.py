"""What the guardian (:mod:`rig.engine.guardian`) finds out besides its pipe, and what it writes
in a run's store: whether the rig process is stopped, whether another process closed the run,
and, when it acted, the run marked incomplete with what it did.

A run closed by another process while the rig was stopped (a reader in another PID namespace found
its lease expired, marked it ``incomplete`` and sealed it: ``seal.json`` appears before the rig has
said ``done``, and the stored status is no longer ``running``) is the third finding: the guardian
switches every output off and writes nothing to the closed run. A rig still stopped is killed
first (it holds its ports and cannot go safe); a running one finds the same and ends through its
own safe path (ADR 0036), guarded meanwhile: one that has not ended
:data:`rig.engine.guardian.CLOSED_GRACE_S` later
is killed, and outputs the guardian could not reach while the rig held them are switched off
once it has ended.
"""

from __future__ import annotations

import json
import os
import sqlite3
import time
from pathlib import Path

from drivers.transport.tty_watch import tty_seen_stall_s
from rig.engine.cpu_wait import CpuWaitLog


def record_in_run(
    folder: Path, t_found: float, why: str, done: list[str], problems: list[str], cpu: str = ""
) -> None:
    """Mark the run incomplete and log what the guardian did (the run's own clock); ``cpu`` is
    the guardian's note on its own wait for a CPU, appended to its message. A run that is no
    longer ``running`` (closed by another process) is left untouched, its seal too."""
    path = folder / "run.sqlite"
    if not path.exists():
        return
    took_ms = 1000.0 * (time.monotonic() - t_found)
    message = (
        f"guardian: {why}; switched off {', '.join(done) or 'nothing'} in {took_ms:.0f} ms{cpu}"
    )
    con = sqlite3.connect(path, timeout=10.0)
    try:
        con.execute("BEGIN IMMEDIATE")  # a run closed meanwhile by another process stays as it is
        row = con.execute("SELECT value FROM meta WHERE key = 'status'").fetchone()
        if row is not None and json.loads(row[0]) != "running":
            con.rollback()
            return
        rows = [(time.monotonic(), "error", message)]
        rows += [(time.monotonic(), "error", f"guardian could not safe {p}") for p in problems]
        con.executemany("INSERT INTO events VALUES (?, ?, ?)", rows)
        con.execute(
            "INSERT OR REPLACE INTO meta VALUES ('status', ?), ('reason', ?)",
            (json.dumps("incomplete"), json.dumps(f"{why}; the guardian switched the outputs off")),
        )
        con.commit()
    finally:
        con.close()
    from rig.store.seal import seal_run

    seal_run(folder)  # the run is closed now: its data never change again


def run_closed_by_other(folder: Path) -> str | None:
    """The status another process stored in the run in ``folder`` when it closed it while the rig
    was not done (``seal.json`` is there and the status is no longer ``running``), else None. One
    ``lstat`` per call while the run has no seal; the store is read only once it has one."""
    if not os.path.lexists(folder / "seal.json"):
        return None
    try:
        con = sqlite3.connect(f"file:{folder / 'run.sqlite'}?mode=ro", uri=True, timeout=1.0)
        try:
            row = con.execute("SELECT value FROM meta WHERE key = 'status'").fetchone()
        finally:
            con.close()
        status = json.loads(row[0]) if row is not None else None
    except (sqlite3.Error, ValueError):
        return None  # not readable: the rig's own writer judges its store
    return None if status in (None, "running") else str(status)


def process_stopped(pid: int) -> bool:
    """True while process ``pid`` is stopped (state T or t in /proc: SIGSTOP, a debugger); a
    process waiting for a CPU (state R) or gone is not."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text(encoding="ascii")
    except OSError:
        return False
    return stat.rsplit(")", 1)[-1].split()[:1] in (["T"], ["t"])


STILL_STOPPED_S = 0.2
"""How long a rig found stopped must stay stopped before the guardian kills it (s): two processes
continued together (a thawed cgroup; a harness continuing the guardian, then the rig) are continued
a moment apart, and beside two CPU hogs the guardian ran in between and killed a rig that was
being continued (it would have ended through its own safe path)."""


def stays_stopped(pid: int, grace_s: float = STILL_STOPPED_S) -> bool:
    """True when process ``pid`` is stopped and still is ``grace_s`` later (polled every 20 ms)."""
    deadline = time.monotonic() + grace_s
    while process_stopped(pid):
        if time.monotonic() >= deadline:
            return True
        time.sleep(0.02)
    return False


CPU_WAIT_LOOKBACK_S = 0.15
"""The guardian's account of its own CPU wait starts at its last round this long before it found
the rig dead or hung (one select period and a margin), so it covers the rig's death and the
guardian's waking to it."""
WORTH_SAYING_S = 0.05
"""A wait shorter than this (s) is not mentioned in the guardian's line."""


def busy_note(waits: CpuWaitLog, t_found: float) -> str:
    """What this computer, not the rig or the hardware, added to the guardian's time to safe since
    ``t_found`` (monotonic s), when worth saying (>= 50 ms): ``; the guardian waited N ms for a
    CPU`` (its threads' longest wait, Linux schedstat) and ``; the terminal layer held serial data
    N ms`` (the kernel's tty worker, as the canary of :mod:`drivers.transport.tty_watch` saw it
    once the guardian opened a serial link: a request to a supply on a pty or USB adapter waits
    there, beside two CPU hogs for seconds)."""
    now = time.monotonic()
    waits.note(now)
    cpu_s = waits.waited_since(t_found - CPU_WAIT_LOOKBACK_S)
    tty_s = tty_seen_stall_s(t_found, now)
    note = (
        f"; the guardian waited {1000.0 * cpu_s:.0f} ms for a CPU"
        if cpu_s >= WORTH_SAYING_S
        else ""
    )
    if tty_s >= WORTH_SAYING_S:
        note += f"; the terminal layer held serial data {1000.0 * tty_s:.0f} ms"
    return note
