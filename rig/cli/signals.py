"""Signals and a closed standard output, for every command in one place.

* Ctrl-C (SIGINT) always stops ``rig`` (:func:`allow_interrupt`); ``main`` turns the resulting
  KeyboardInterrupt into exit code 130.
* Commands that hold outputs or serve until stopped (``rig sim``, ``rig cage ...``) turn SIGINT and
  SIGTERM into a stop request with :func:`stop_on_signals`. A procedure run (``rig run``, ``rig
  demo``) is handled by the engine's runner, which also treats SIGHUP as a stop.
* A reader of our output that went away (``rig show RUN | head``): exit 141 without a word, as a
  tool killed by SIGPIPE (:func:`stdout_closed`, :func:`quiet_exit_on_closed_pipe`).
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

EXIT_CLOSED_PIPE = 128 + 13
"""Like a tool killed by SIGPIPE: the reader of our output (``| head``) has gone."""


def allow_interrupt() -> None:
    """Ctrl-C (SIGINT) always stops the rig, even when a non-interactive shell started it in the
    background with SIGINT ignored (the shell's convention): a run that cannot be interrupted is
    worse than a script that has to say so."""
    if threading.current_thread() is threading.main_thread():
        if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


@contextmanager
def stop_on_signals(stop: threading.Event, *, interrupt: bool) -> Iterator[None]:
    """While inside, SIGINT and SIGTERM set ``stop``; with ``interrupt`` they also raise
    KeyboardInterrupt in the main thread (to leave a blocking call through the safe path). The
    previous handlers are restored on exit."""

    def handler(signum: int, frame: FrameType | None) -> None:
        stop.set()
        if interrupt:
            raise KeyboardInterrupt

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def stdout_closed() -> bool:
    """True when standard output is a pipe whose reader has gone."""
    import select

    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # replaced by a test's capture, or closed
        return False
    poll = select.poll()
    poll.register(fd, select.POLLOUT)
    return any(ev & select.POLLERR for _, ev in poll.poll(0))


def quiet_exit_on_closed_pipe() -> int:
    """Point stdout at /dev/null so that the interpreter's final flush cannot fail again, and
    exit without a word (the reader chose to stop reading)."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return EXIT_CLOSED_PIPE
