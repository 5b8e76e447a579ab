"""A frozen recorder whose run a reader closed (issue 51): recorder and guardian SIGSTOPped, a
reader in another PID namespace finds the lease expired, marks the run incomplete and seals it; on
SIGCONT the guardian switches every output off, the rig ends ``error`` through its safe path, and
neither touches the reader's status, data or seal (ADR 0036).

The reader is the project's own (``RunReader``, as ``rig runs`` opens a run) in a new PID namespace
(``unshare``, as root; skipped with the reason elsewhere), with the lease's expiry shortened in that
process only (``LEASE_EXPIRY_S`` 2 s, ``LEASE_WATCH_S`` 1 s) so the freeze lasts seconds, not 35 s.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench.faultlab import guardian_cpu_wait_ms, guardian_of, killed_rig_end_ms
from drivers.transport.tty_watch import tty_watch
from rig.engine.cpu_priority import GUARDIAN_NICE
from rig.engine.recording import AFTER_CLOSE_FILE
from sim.cage import SimulatedCage
from tests.computer_delay import ComputerDelay
from tests.engine.test_guardian_pair import OUTPUTS_OFF_WITHIN_S, off_after, start_run
from tests.sim.nice import nice_of
from tests.store.test_run_lease import other_namespace, status_of

pytestmark = [pytest.mark.realtime, pytest.mark.usefixtures("own_lock_dir")]

RIG = [sys.executable, "-m", "rig.cli"]
EXPIRY_S = 2.0
READER = f"""
import sys
from pathlib import Path
import rig.store.run_store as store
store.LEASE_EXPIRY_S, store.LEASE_WATCH_S = {EXPIRY_S}, 1.0  # this reader only
reader = store.RunReader(Path(sys.argv[1]))
print(reader.meta()["status"])
"""


def reader_elsewhere(folder: Path) -> str:
    """Open the run with ``RunReader`` in another PID namespace; the status it leaves."""
    done = subprocess.run([*other_namespace(), sys.executable, "-c", READER, str(folder)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_a_run_sealed_by_a_reader_while_stopped_ends_error_outputs_off_seal_kept(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path
) -> None:
    other_namespace()
    tty_watch()  # the canary runs before the freeze, so it sees the whole window
    child, runs = start_run(rig_toml, tmp_path)
    try:
        guardian = guardian_of(child.pid)
        folder = next(p for p in runs.iterdir() if (p / "run.sqlite").exists())
        supplies = cage.physics.supplies
        assert any(s.output for s in supplies.values())
        os.kill(child.pid, signal.SIGSTOP)  # the rig first: a stopped guardian is a fault of its
        os.kill(guardian, signal.SIGSTOP)
        time.sleep(EXPIRY_S + 0.5)
        assert reader_elsewhere(folder) == "incomplete"
        by_reader = status_of(folder)
        seal = (folder / "seal.json").read_bytes()
        assert by_reader["status"] == "incomplete" and "stopped renewing its lease" in str(
            by_reader["reason"]
        )
        assert all(s.output for s in (supplies[n] for n in ("coil_x", "coil_y", "coil_z")))
        on = tuple(n for n, s in supplies.items() if s.output)
        # the cage's waits for a CPU (it records when each output went off) and the terminal
        # layer's hold (coil_y is on a pty) are this computer's, not the guardian's: with four
        # workers on two cores the cage once recorded the guardian's 180 ms switch-off 1124 ms
        # after SIGCONT, and once every output off 3481 ms after it with the guardian's wait 0
        t_cont, computer = time.monotonic(), ComputerDelay()
        os.kill(guardian, signal.SIGCONT)
        os.kill(child.pid, signal.SIGCONT)
        took = off_after(cage, t_cont, on, 30.0) - computer.seconds()
        _, err = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert "Traceback" not in err, err
    assert child.returncode == 2, err
    assert "rig: error: run" in err and "closed by another process while this one was stopped" in (
        err
    ), err
    assert "rig guardian: the run was closed by another process" in err, err
    # the reader's record stands: its status and reason, its seal byte for byte, its data
    assert status_of(folder) == by_reader
    assert (folder / "seal.json").read_bytes() == seal
    verify = subprocess.run([*RIG, "verify", str(folder)], capture_output=True, text=True,
                            timeout=60)  # fmt: skip
    assert verify.returncode == 0, verify.stdout + verify.stderr
    note = json.loads((folder / AFTER_CLOSE_FILE).read_text())
    assert note["line"].startswith("the run was closed by another process"), note
    assert note["would_have_stored"].startswith("error:"), note
    manifest = json.loads((folder / "manifest.json").read_text())
    assert AFTER_CLOSE_FILE in manifest["files"], manifest
    assert not any(s.output for s in supplies.values())  # those that were off too
    print(f"run sealed by a reader while stopped: {', '.join(on)} off {1000 * took:.0f} ms after"
          f" SIGCONT; rows not stored {note['rows_not_stored']}")  # fmt: skip
    # plus the guardian's own measured wait for a CPU (a busy computer's, not the rig's: as in
    # the fault matrix); beside two CPU hogs it once waited 1525 ms
    assert took < OUTPUTS_OFF_WITHIN_S + guardian_cpu_wait_ms(err) / 1000.0, err


def test_the_guardian_alone_acts_on_the_reader_seal_and_kills_a_rig_still_stopped(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path
) -> None:
    """Only the guardian resumes: it finds the run closed and the rig still stopped, kills the rig
    (which holds its serial ports and cannot go safe) and switches every output off; the reader's
    record stands."""
    other_namespace()
    tty_watch()  # the canary runs before the freeze, so it sees the whole window
    child, runs = start_run(rig_toml, tmp_path)
    try:
        guardian = guardian_of(child.pid)
        # a safety watchdog asks for a CPU first where the system allows it (here as root)
        assert os.geteuid() != 0 or nice_of(guardian, guardian) == GUARDIAN_NICE
        folder = next(p for p in runs.iterdir() if (p / "run.sqlite").exists())
        supplies = cage.physics.supplies
        os.kill(child.pid, signal.SIGSTOP)
        os.kill(guardian, signal.SIGSTOP)
        time.sleep(EXPIRY_S + 0.5)
        assert reader_elsewhere(folder) == "incomplete"
        by_reader, seal = status_of(folder), (folder / "seal.json").read_bytes()
        on = tuple(n for n, s in supplies.items() if s.output)
        assert on
        # the cage's waits for a CPU (it records when each output went off) and the terminal
        # layer's hold (coil_y is on a pty) are this computer's, not the guardian's: with four
        # workers on two cores the cage once recorded the guardian's 180 ms switch-off 1124 ms
        # after SIGCONT, and once every output off 3481 ms after it with the guardian's wait 0
        t_cont, computer = time.monotonic(), ComputerDelay()
        os.kill(guardian, signal.SIGCONT)
        took = off_after(cage, t_cont, on, 30.0) - computer.seconds()
        _, err = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == -signal.SIGKILL, err
    assert "rig guardian: the run was closed by another process" in err, err
    assert "the rig process was still stopped and was killed; switched off coil_x, coil_y" in err
    assert "WARNING" not in err, err
    assert status_of(folder) == by_reader
    assert (folder / "seal.json").read_bytes() == seal
    verify = subprocess.run([*RIG, "verify", str(folder)], capture_output=True, text=True,
                            timeout=60)  # fmt: skip
    assert verify.returncode == 0, verify.stdout + verify.stderr
    print(
        f"guardian alone: {', '.join(on)} off {1000 * took:.0f} ms after its SIGCONT: {err.strip()}"
    )
    # plus the guardian's own measured wait for a CPU and the killed rig's end (the kernel's
    # teardown, which frees its ports): a busy computer's, not the rig's, as in the fault matrix.
    # Beside two CPU hogs and four workers the guardian once took 3931 ms here, saying neither.
    assert (
        took < OUTPUTS_OFF_WITHIN_S + (guardian_cpu_wait_ms(err) + killed_rig_end_ms(err)) / 1000.0
    ), err
