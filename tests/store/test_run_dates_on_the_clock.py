"""A run's own times and dates are on the process's clock (ADR 0038); its lease, read by other
processes, stays on the wall clock; ``rig runs`` leaves a dead simulated run's outputs alone."""

from __future__ import annotations

import datetime as dt
import time
from pathlib import Path

import pytest

import timebase
from rig.store.run_store import RunInfo, RunReader, new_run


def test_a_run_in_simulated_time_is_dated_in_simulated_time(tmp_path: Path) -> None:
    epoch = dt.datetime(2031, 3, 4, 5, 6, 7, tzinfo=dt.UTC).timestamp()
    with timebase.simulated(start_s=50.0, epoch_s=epoch):
        w = new_run(tmp_path, "sim", procedure="p")
        timebase.sleep(10.0)
        w.add_event(timebase.monotonic(), "info", "ten seconds in")
        w.close("complete", "all steps done")
    reader = RunReader(w.folder)
    try:
        meta, events = reader.meta(), reader.events()
    finally:
        reader.close()
    assert w.folder.name == "20310304-050607-sim"
    assert meta["clock"] == "simulated"
    assert meta["start_time"] == "2031-03-04T05:06:07.000+00:00"
    assert meta["start_monotonic"] == 50.0
    assert meta["end_time"] == "2031-03-04T05:06:17+00:00"
    assert events == [(60.0, "info", "ten seconds in")]
    # the lease is for other processes: their clock is the wall clock
    assert meta["lease"]["renewed_at"] == pytest.approx(time.time(), abs=60.0)


def test_a_run_on_the_wall_clock_says_so(tmp_path: Path) -> None:
    w = new_run(tmp_path, "wall", procedure="p")
    w.close("complete", "done")
    reader = RunReader(w.folder)
    try:
        meta = reader.meta()
    finally:
        reader.close()
    assert meta["clock"] == "wall"
    start = dt.datetime.fromisoformat(meta["start_time"]).timestamp()
    assert start == pytest.approx(time.time(), abs=60.0)


def test_rig_runs_leaves_a_dead_simulated_run_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from rig.cli.runs import switch_off_after

    run = RunInfo("20310304-050607-sim", tmp_path, {"clock": "simulated", "status": "running"},
                  closed_now=True)  # fmt: skip
    switch_off_after(run)  # no rig.toml: on the wall clock this would warn it cannot be read
    err = capsys.readouterr().err
    assert "ran in simulated time" in err and "nothing to switch off" in err
