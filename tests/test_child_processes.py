"""Child processes never outlive the test: rig.child_process and tests/simproc.py."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from rig.child_process import start_child, stop_child
from tests.simproc import sim_process

pytestmark = pytest.mark.realtime

linux_only = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux-only"
)


def alive(pid: int) -> bool:
    """The process exists and is not a zombie (a zombie has already died)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            state = f.read().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")


def wait_gone(pid: int, deadline_s: float) -> bool:
    """Poll until ``pid`` has gone or ``deadline_s`` (s) passed; True when it has gone."""
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        if not alive(pid):
            return True
        time.sleep(0.05)
    return not alive(pid)


def kill_quietly(pid: int) -> None:
    """Clean up after a failed assertion: never leave the child behind."""
    if alive(pid):
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)


PARENT = textwrap.dedent(
    """
    import sys, time
    from rig.child_process import start_child
    child = start_child([sys.executable, "-c", "import time; time.sleep(120)"])
    print(child.pid, flush=True)
    time.sleep(120)
    """
)


@linux_only
def test_child_dies_when_its_parent_is_sigkilled() -> None:
    parent = subprocess.Popen([sys.executable, "-c", PARENT], stdout=subprocess.PIPE, text=True)
    child_pid = 0
    try:
        assert parent.stdout is not None
        child_pid = int(parent.stdout.readline())
        assert alive(child_pid)
        parent.kill()  # SIGKILL: no finally, no atexit in the parent
        parent.wait(timeout=30)
        # Generous deadline: the kernel signals at once; a loaded machine may take a while to run
        # the child's exit.
        assert wait_gone(child_pid, 30.0), f"child {child_pid} outlived its SIGKILLed parent"
    finally:
        stop_child(parent, first=signal.SIGKILL, wait_s=30.0)  # its pipe closed, whatever came
        if child_pid:
            kill_quietly(child_pid)


STUBBORN_SIM = textwrap.dedent(
    """
    import json, os, pathlib, signal, sys, time
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a simulator that ignores Ctrl-C
    args = dict(zip(sys.argv[1::2], sys.argv[2::2]))
    pathlib.Path(args["--endpoints-json"]).write_text(json.dumps({"devices": {"pid": os.getpid()}}))
    pathlib.Path(args["--rig-config"]).write_text("")
    time.sleep(120)
    """
)


def test_sim_process_kills_a_child_that_ignores_sigint(tmp_path: Path) -> None:
    with sim_process(tmp_path, [sys.executable, "-c", STUBBORN_SIM], stop_wait_s=1.0) as (_, devs):
        pid = int(devs["pid"])
        assert alive(pid)
    try:
        assert not alive(pid), "sim_process returned with its child still running"
    finally:
        kill_quietly(pid)


def test_stop_child_closes_the_pipes_of_a_child_that_has_gone() -> None:
    """A stopped child's pipes are closed (left to the collector they were a ResourceWarning in a
    later test); one that would not go keeps them (it may still write)."""
    child = start_child([sys.executable, "-c", "import time; print('up', flush=True); time.sleep(60)"],
                        stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    assert child.stdout is not None and child.stdout.readline() == b"up\n"
    assert stop_child(child, first=signal.SIGTERM, wait_s=10.0) == -signal.SIGTERM
    assert child.stdout.closed and child.stderr is not None and child.stderr.closed
