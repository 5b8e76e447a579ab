"""The run store: round trip, batch commits, a killed writer loses at most 0.5 s, exports."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rig.store import RunReader, list_runs, new_run
from rig.store.export import export_csv, export_hdf5


def test_round_trip_and_status(tmp_path: Path) -> None:
    w = new_run(tmp_path, "DUT 42/a", operator="ana", dut_serial="42")
    assert w.folder.name.endswith("-DUT-42-a")
    for i in range(100):
        w.add_sample(float(i), "dut", (1.0 * i, 2.0, 3.0))
        w.add_channel(float(i), "load1", 0.5, 0.499)
    w.add_event(0.0, "info", "started")
    w.set_step(0, "sweep", "sphere_sweep", 0.0, 99.0)
    w.set_result("calibration", {"a": 1.0})
    w.close("complete", "finished")
    r = RunReader(w.folder)
    meta = r.meta()
    assert (
        meta["status"] == "complete" and meta["operator"] == "ana" and meta["reason"] == "finished"
    )
    assert r.count("samples") == 100 and r.samples("dut")[5] == (5.0, 5.0, 2.0, 3.0)
    assert r.channel("load1")[0] == (0.0, 0.5, 0.499)
    assert r.results() == {"calibration": {"a": 1.0}}
    runs = list_runs(tmp_path)
    assert [x.run_id for x in runs] == [w.folder.name] and runs[0].status == "complete"


WRITER = """
import sys, time
from pathlib import Path
from rig.store import new_run
w = new_run(Path(sys.argv[1]), "killme")
print(w.folder, flush=True)
while True:
    t = time.monotonic()
    w.add_sample(t, "dut", (t, 0.0, 0.0))
    time.sleep(0.001)
"""


def test_sigkill_loses_at_most_half_a_second(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(tmp_path)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    folder = Path(proc.stdout.readline().strip())
    time.sleep(1.5)
    t_kill = time.monotonic()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    r = RunReader(folder)  # opening it marks the killed run incomplete
    meta = r.meta()
    assert meta["status"] == "incomplete" and "killed" in meta["reason"]
    rows = r.samples("dut")
    assert len(rows) > 500
    lost_s = t_kill - rows[-1][0]
    assert lost_s <= 0.5, f"{lost_s:.3f} s of samples lost"
    r.close()


def test_exports(tmp_path: Path) -> None:
    w = new_run(tmp_path / "runs", "x")
    for i in range(10):
        w.add_sample(float(i), "ref", (float(i), 0.0, -1.0))
    w.add_channel(1.0, "coil_x", 0.25, None)
    w.close("complete", "ok")
    r = RunReader(w.folder)
    files = export_csv(r, tmp_path / "csv")
    assert (tmp_path / "csv" / "samples_ref.csv").read_text().splitlines()[1] == "0.0,0.0,0.0,-1.0,"
    assert len(files) == 4
    h5py = pytest.importorskip("h5py")
    export_hdf5(r, tmp_path / "run.h5")
    with h5py.File(tmp_path / "run.h5") as f:
        np.testing.assert_array_equal(f["samples/ref"][3], [3.0, 3.0, 0.0, -1.0])
        assert np.isnan(f["channels/coil_x"][0][2])


def test_not_a_run_folder(tmp_path: Path) -> None:
    from rig.errors import UserInputError

    with pytest.raises(UserInputError, match="not a run folder"):
        RunReader(tmp_path)
