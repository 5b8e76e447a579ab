"""Run status by lease, not PID (issue 29): a reader in another PID namespace (a container, another
host sharing the runs folder) never marks a live run incomplete, and marks one whose lease has
expired.

The readers run ``rig runs`` under ``unshare --pid --fork --mount-proc`` (as root; skipped with the
reason where that is not permitted), so they see none of the recorder's processes, as a container
would. The recorders are real: ``rig run`` on the simulated cage, and a writer process of the store.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from rig import host_identity
from rig.child_process import stop_child
from rig.store import new_run
from rig.store.run_store import LEASE_EXPIRY_S, LEASE_WATCH_S, RunReader
from tests.simproc import outputs, sim_process

pytestmark = pytest.mark.realtime

RIG = [sys.executable, "-m", "rig.cli"]

LONG_RUN = """
procedure: Lease
magnetometers: {dut: dut, reference: reference}
steps:
  - set_field: {field_ut: [20, 0, 0], hold_s: 60}
"""

STOPPED_CLOCK_WRITER = """
import sys, time
from pathlib import Path
time.time = lambda: 1_000_000_000.0  # the recorder's host clock, stopped in 2001
from rig import host_identity
from rig.store import new_run
w = new_run(Path(sys.argv[1]), "stopped-clock")
print(w.folder, flush=True)
while True:
    time.sleep(0.05)
    w.add_sample(time.monotonic(), "dut", (0.0, 0.0, 0.0))
"""


def other_namespace() -> list[str]:
    """The command prefix of a reader in a new PID namespace, or a skip with the reason."""
    if shutil.which("unshare") is None:
        pytest.skip("unshare (util-linux) is not installed")
    probe = subprocess.run(["unshare", "--pid", "--fork", "--mount-proc", "true"],
                           capture_output=True, text=True, timeout=30)  # fmt: skip
    if probe.returncode != 0:
        pytest.skip(f"cannot make a PID namespace here: {probe.stderr.strip()}")
    return ["unshare", "--pid", "--fork", "--mount-proc"]


READER = """
import os, sys
print(os.stat("/proc/self/ns/pid").st_ino, os.getpid(), flush=True)
from rig.cli import main
sys.exit(main(["runs", "--runs-dir", sys.argv[1]]))
"""


def rig_runs_elsewhere(runs: Path) -> tuple[str, int]:
    """`rig runs --runs-dir RUNS` in another PID namespace: (its output, its namespace inode).
    Asserts the reader really was elsewhere: another namespace, where it is PID 1."""
    done = subprocess.run([*other_namespace(), sys.executable, "-c", READER, str(runs)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 0, done.stderr
    first, _, listing = done.stdout.partition("\n")
    inode, pid = (int(x) for x in first.split())
    assert inode != os.stat("/proc/self/ns/pid").st_ino and pid == 1, first
    return listing, inode


def status_of(folder: Path) -> dict[str, object]:
    """The run's meta, read without a RunReader (which could itself mark the run)."""
    con = sqlite3.connect(f"file:{folder / 'run.sqlite'}?mode=ro", uri=True, timeout=10)
    try:
        return {k: json.loads(v) for k, v in con.execute("SELECT key, value FROM meta")}
    finally:
        con.close()


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[tuple[Path, dict[str, object]]]:
    with sim_process(tmp_path / "sim") as (rig_toml, devices):
        yield rig_toml, devices


def test_a_reader_in_another_pid_namespace_leaves_a_live_run_running(
    sim: tuple[Path, dict[str, object]], tmp_path: Path
) -> None:
    """The attack of issue 29: `rig runs` in a container marked a live run incomplete and sealed it
    while it recorded with coils on; the page then refused Abort."""
    other_namespace()
    rig_toml, devices = sim
    proc_file = tmp_path / "lease.yaml"
    proc_file.write_text(LONG_RUN)
    runs = tmp_path / "runs"
    run = subprocess.Popen([*RIG, "-q", "run", str(proc_file), "--rig", str(rig_toml), "--yes",
                            "--runs-dir", str(runs)], stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        folder = None
        while folder is None or not status_of(folder).get("cage_model"):  # devices open
            assert run.poll() is None and time.monotonic() < deadline, run.stderr
            time.sleep(0.1)
            found = list(runs.glob("*/run.sqlite")) if runs.exists() else []
            folder = found[0].parent if found else None
        while not any(outputs(devices, tcp_only=True).values()):  # the field is on
            assert run.poll() is None and time.monotonic() < deadline
            time.sleep(0.1)
        seq = status_of(folder)["lease"]["seq"]  # type: ignore[index]
        for _ in range(2):
            listing, _ = rig_runs_elsewhere(runs)
            assert f"{folder.name} running" in listing, listing
        assert not (folder / "seal.json").exists()
        assert run.poll() is None and any(outputs(devices, tcp_only=True).values())
        while status_of(folder)["lease"]["seq"] == seq:  # type: ignore[index]
            assert time.monotonic() < deadline, "the recorder stopped renewing its lease"
            time.sleep(0.1)
        assert status_of(folder)["status"] == "running"
        listing, _ = rig_runs_elsewhere(runs)  # and once more, on a renewed lease
        assert f"{folder.name} running" in listing and not (folder / "seal.json").exists()
        run.send_signal(signal.SIGINT)
        assert run.wait(timeout=60) == 130
    finally:
        stop_child(run, first=signal.SIGKILL)  # ended or not: its pipe closed
    assert status_of(folder)["status"] == "aborted" and (folder / "seal.json").exists()


def test_a_stopped_clock_is_not_an_expired_lease_and_a_dead_recorder_is_found(
    tmp_path: Path,
) -> None:
    """A recorder whose host's clock stopped long ago renews a lease that looks decades old: the
    reader in another namespace sees it renewed within LEASE_WATCH_S and leaves the run running.
    Killed (no guardian), its lease stops: the next such reader marks it incomplete and seals it."""
    other_namespace()
    runs = tmp_path / "runs"
    writer = subprocess.Popen([sys.executable, "-c", STOPPED_CLOCK_WRITER, str(runs)],
                              stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert writer.stdout is not None
        folder = Path(writer.stdout.readline().strip())
        assert status_of(folder)["lease"]["renewed_at"] == 1e9  # type: ignore[index]
        listing, _ = rig_runs_elsewhere(runs)
        assert f"{folder.name} running" in listing, listing
        assert not (folder / "seal.json").exists()
    finally:
        stop_child(writer, first=signal.SIGKILL)  # its pipe closed too
    t0 = time.monotonic()
    listing, _ = rig_runs_elsewhere(runs)
    assert time.monotonic() - t0 >= LEASE_WATCH_S  # it watched before it judged
    assert f"{folder.name} incomplete" in listing, listing
    meta = status_of(folder)
    assert meta["status"] == "incomplete" and "stopped renewing its lease" in str(meta["reason"])
    assert "killed" in str(meta["reason"]) and (folder / "seal.json").exists()


def test_a_lease_of_another_boot_is_judged_by_its_time_not_by_its_pid(tmp_path: Path) -> None:
    """A folder written on another host (or before a reboot): its PID means nothing here. A fresh
    lease keeps it running though no such PID exists; one past LEASE_EXPIRY_S that does not move
    is expired. Same namespace, the PID decides at once (a killed recorder, no wait)."""
    writer = new_run(tmp_path / "runs", "elsewhere")
    folder = writer.folder
    writer.close("complete", "done")

    def craft(**lease: object) -> None:
        con = sqlite3.connect(folder / "run.sqlite")
        old = json.loads(con.execute("SELECT value FROM meta WHERE key='lease'").fetchone()[0])
        con.execute("INSERT OR REPLACE INTO meta VALUES ('status', ?), ('lease', ?)",
                    (json.dumps("running"), json.dumps(old | lease)))  # fmt: skip
        con.commit()
        con.close()
        (folder / "seal.json").unlink(missing_ok=True)

    dead_pid = 2**22 + 7  # beyond pid_max: no such process here
    craft(boot_id="another-boot", pid=dead_pid, renewed_at=time.time())
    RunReader(folder).close()
    assert status_of(folder)["status"] == "running" and not (folder / "seal.json").exists()
    craft(boot_id="another-boot", pid=dead_pid, renewed_at=time.time() - 2 * LEASE_EXPIRY_S)
    RunReader(folder).close()
    assert status_of(folder)["status"] == "incomplete" and (folder / "seal.json").exists()
    # this boot and namespace, a PID that does not exist: the fast path, no watching
    # (the lease is fresh: judged by it, the run would stay running)
    craft(boot_id=host_identity.boot_id(), pid=dead_pid, renewed_at=time.time(), pid_start=None)
    RunReader(folder).close()
    meta = status_of(folder)
    assert meta["status"] == "incomplete" and "ended without closing" in str(meta["reason"])
