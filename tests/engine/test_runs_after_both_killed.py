"""Both the rig and its guardian killed (issue 51): coils and a load stayed on, and `rig runs`
marked the run incomplete and touched nothing. Now the listing that finds the run dead switches
every output of the run's copy of its rig configuration off and reads it back, unless a command
holds them; on the simulated cage over real Modbus, with real processes and signals."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench.faultlab import guardian_of
from rig.child_process import stop_child
from rig.store import RunReader
from sim.cage import SimulatedCage
from tests.engine.test_guardian_pair import DRIVEN, start_run

RIG = [sys.executable, "-m", "rig.cli"]

pytestmark = [pytest.mark.realtime, pytest.mark.usefixtures("own_lock_dir")]


def kill_both(child: subprocess.Popen[str]) -> None:
    """Stop the rig and its guardian (neither can act), then kill both."""
    guardian = guardian_of(child.pid)
    for pid in (child.pid, guardian):
        os.kill(pid, signal.SIGSTOP)
    for pid in (child.pid, guardian):
        os.kill(pid, signal.SIGKILL)
    stop_child(child, first=signal.SIGKILL, wait_s=10.0)  # reaped, its pipes closed
    for _ in range(500):  # the guardian is no child of ours: wait until it is gone
        try:
            os.kill(guardian, 0)
        except ProcessLookupError:
            return
        time.sleep(0.01)


def test_rig_runs_switches_off_what_a_dead_run_left_on(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path
) -> None:
    child, runs = start_run(rig_toml, tmp_path)
    kill_both(child)
    supplies = cage.physics.supplies
    assert all(supplies[n].output for n in DRIVEN), "the outputs were left on by the kill"
    listed = subprocess.run([*RIG, "runs", "--runs-dir", str(runs)], capture_output=True,
                            text=True, timeout=60)  # fmt: skip
    assert listed.returncode == 0, listed
    assert "ended without its recorder or guardian: its outputs switched off and read back" in (
        listed.stderr
    ), listed.stderr
    assert not any(s.output for s in supplies.values()), [
        n for n, s in supplies.items() if s.output
    ]
    assert " incomplete " in listed.stdout, listed.stdout
    # the next listing finds nothing to do: the run is closed
    again = subprocess.run([*RIG, "runs", "--runs-dir", str(runs)], capture_output=True,
                           text=True, timeout=60)  # fmt: skip
    assert "ended without" not in again.stderr, again.stderr
    folder = next(p for p in runs.iterdir() if (p / "run.sqlite").exists())
    reader = RunReader(folder)
    try:
        assert reader.meta()["status"] == "incomplete"
    finally:
        reader.close()
