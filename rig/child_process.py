"""Child processes that do not outlive their parent (Linux), and a stop that always ends them.

:func:`start_child` is :class:`subprocess.Popen` plus, on Linux, ``prctl(PR_SET_PDEATHSIG,
SIGTERM)`` in the child between fork and exec: the kernel sends the child SIGTERM when its parent
goes away, however it goes (SIGKILL, OOM killer, a crashed interpreter), where no ``finally`` of the
parent runs. On other systems, or where libc has no ``prctl``, it is plain ``Popen`` (no-op).

Two limits of the kernel mechanism, both documented in ``prctl(2)``:

* The signal fires when the parent *thread* that forked the child exits, not when the process
  does. Call :func:`start_child` only from a thread that lives as long as the child (the main
  thread, or the thread that also stops the child); a short-lived worker thread would take its
  children with it.
* The child must die of SIGTERM: the default action does, and ``rig sim`` stops cleanly on it.
  A program that ignores SIGTERM is not covered.

Not for the guardian (``rig.engine.guardian``): it exists to outlive a killed rig process.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Sequence
from typing import Any

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _death_signal_hook(sig: int) -> Callable[[], None] | None:
    """A ``preexec_fn`` that asks the kernel for ``sig`` when the parent thread exits; ``None``
    where that is not available. The C function is looked up here, in the parent, so that the
    forked child only calls it (no imports or library loading between fork and exec)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        prctl = libc.prctl
    except (OSError, AttributeError):
        return None
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    prctl.restype = ctypes.c_int
    parent = os.getpid()

    def hook() -> None:
        prctl(PR_SET_PDEATHSIG, sig, 0, 0, 0)
        if os.getppid() != parent:  # the parent died before prctl: no signal will come
            os._exit(1)

    return hook


def start_child(
    argv: Sequence[str], *, death_signal: int = signal.SIGTERM, **popen_kwargs: Any
) -> subprocess.Popen[bytes]:
    """Start ``argv`` like :class:`subprocess.Popen` (``popen_kwargs`` passed on; no
    ``preexec_fn`` of your own, and bytes I/O), with ``death_signal`` sent to the child when the
    calling thread exits (Linux; elsewhere plain ``Popen``)."""
    if "preexec_fn" in popen_kwargs:
        raise TypeError("start_child sets preexec_fn itself")
    return subprocess.Popen(list(argv), preexec_fn=_death_signal_hook(death_signal), **popen_kwargs)


def stop_child(
    proc: subprocess.Popen[Any],
    *,
    first: int = signal.SIGINT,
    wait_s: float = 15.0,
    kill_wait_s: float = 5.0,
) -> int | None:
    """Ask the child to stop with ``first`` (default SIGINT, a Ctrl-C), wait up to ``wait_s``
    (s), then SIGKILL it and wait up to ``kill_wait_s`` (s) more. Returns its exit code (negative:
    the signal that ended it), or ``None`` if it still has not gone (not ours to wait for ever).
    Once it has gone, its pipes are closed (what it wrote and nobody read is dropped)."""
    code = _stopped(proc, first, wait_s, kill_wait_s)
    if code is not None:
        for pipe in (proc.stdin, proc.stdout, proc.stderr):
            if pipe is not None:
                with contextlib.suppress(OSError):  # a broken pipe's unflushed input
                    pipe.close()
    return code


def _stopped(proc: subprocess.Popen[Any], first: int, wait_s: float,
             kill_wait_s: float) -> int | None:  # fmt: skip
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):  # it ended meanwhile
            proc.send_signal(first)
        try:
            return proc.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            proc.kill()
    try:
        return proc.wait(timeout=kill_wait_s)
    except subprocess.TimeoutExpired:
        return None


def process_alive(pid: int) -> bool:
    """The process ``pid`` exists and is not a zombie (a zombie holds no descriptors and does
    nothing more). Another user's process counts as alive."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):  # no /proc (not Linux), or the process has gone
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True
