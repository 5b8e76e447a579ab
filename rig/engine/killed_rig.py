"""The guardian's SIGKILL of its rig, and how long the kernel took to end it.

A killed process's serial ports are free only once the kernel has torn it down, which on a busy
computer waits for a CPU too. The guardian waits for that only briefly before it switches off what
it can reach (a TCP supply is not held by the rig; a held port is retried); the rig's end of the
heartbeat pipe closing says when the rig had ended, and the guardian's line says it when it was slow.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import threading
import time
from collections.abc import Callable

END_WAIT_S = 10.0
"""How long the rig's end is watched for after the kill (s); beyond it the line says so."""
SAY_END_AFTER_S = 0.05
"""A rig that took longer than this (s) to end is named in the guardian's line."""
FIRST_WAIT_S = 0.25
"""How long the kill waits for the rig's end before the switch-off starts (s): its serial ports
are free once it has ended (usually within 70 ms, even beside CPU hogs), and waiting longer than
the switch-off's own retry pause (``RETRY_PAUSE_S``, 0.2 s) gains nothing over retrying."""


def kill_rig(fd: int, pid: int) -> Callable[[], str]:
    """SIGKILL the rig (``pid``; ``fd`` our end of its heartbeat pipe, read by nothing else from
    now on), wait up to :data:`FIRST_WAIT_S` for its end and watch on beside the caller. The
    returned function waits for that watch (up to :data:`END_WAIT_S` after the kill) and gives
    ``"; the killed rig took 940 ms to end"`` when that took longer than
    :data:`SAY_END_AFTER_S`, else ``""``."""
    t0 = time.monotonic()
    with contextlib.suppress(OSError):
        os.kill(pid, signal.SIGKILL)
    ended: list[float] = []

    def watch() -> None:
        deadline = t0 + END_WAIT_S
        while (left := deadline - time.monotonic()) > 0:
            if not select.select([fd], [], [], left)[0]:
                continue
            try:
                chunk = os.read(fd, 4096)
            except OSError:
                chunk = b""
            if not chunk:  # the pipe's far end closed: the kernel has ended the rig
                ended.append(time.monotonic() - t0)
                return

    watcher = threading.Thread(target=watch, name="killed-rig-end", daemon=True)
    watcher.start()
    watcher.join(timeout=FIRST_WAIT_S)

    def said() -> str:
        watcher.join(timeout=max(0.0, t0 + END_WAIT_S - time.monotonic()))
        if not ended:
            return f"; the killed rig had not ended {END_WAIT_S:g} s after its kill"
        took_s = ended[0]
        return (
            f"; the killed rig took {1000.0 * took_s:.0f} ms to end"
            if took_s >= SAY_END_AFTER_S
            else ""
        )

    return said
