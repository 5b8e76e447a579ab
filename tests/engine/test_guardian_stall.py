"""The guardian's timeout measures the rig, not the guardian: time the guardian itself did not run
(stopped here with SIGSTOP, on a bench a busy computer) is added to the rig's allowance, and no
more (it used to restart the whole timeout)."""

from __future__ import annotations

import array
import fcntl
import os
import re
import signal
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest

from rig.engine.guardian import HEARTBEAT_TIMEOUT_S
from tests.waiting import wait_until

pytestmark = pytest.mark.realtime

WAIT = "import sys; from rig.engine.guardian import wait_for_rig; print(wait_for_rig(0, int(sys.argv[1])))"


def unread(fd: int) -> int:
    """Bytes waiting in the pipe whose read end is ``fd``."""
    buf = array.array("i", [0])
    fcntl.ioctl(fd, termios.FIONREAD, buf)
    return buf[0]


def state(pid: int) -> str:
    """The process's state letter (R, S, T for stopped, ...) from /proc."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]


def test_the_guardians_own_stall_is_added_to_the_timeout_and_no_more() -> None:
    victim = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    r, w = os.pipe()
    guardian = subprocess.Popen([sys.executable, "-c", WAIT, str(victim.pid)], stdin=r,
                                stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        os.write(w, b".")  # the last heartbeat
        # read by the guardian: it has started and is waiting (its start may take seconds)
        wait_until(lambda: unread(r) == 0, 60, "the guardian to read the heartbeat")
        time.sleep(0.3)  # the rig's silence before the guardian stalls (part of the scenario)
        guardian.send_signal(signal.SIGSTOP)
        wait_until(lambda: state(guardian.pid) == "T", 30, "the guardian to be stopped")
        time.sleep(1.5)  # the guardian's own stall (the scenario, not a wait for anything)
        guardian.send_signal(signal.SIGCONT)
        out, _ = guardian.communicate(timeout=30)
    finally:
        os.close(r)
        os.close(w)
        guardian.kill()
        victim.kill()
        victim.wait()
    assert victim.returncode == -signal.SIGKILL
    said = re.search(r"no heartbeat for ([0-9.]+) s, ([0-9.]+) s more while the guardian", out)
    assert said, out
    silent_s, own_s = float(said.group(1)), float(said.group(2))
    assert own_s >= 1.4, out
    assert HEARTBEAT_TIMEOUT_S <= silent_s < HEARTBEAT_TIMEOUT_S + 0.1 + 0.6, (
        out
    )  # a check per 0.1 s; stalls under 0.5 s count
