"""The lab trend keeps calibrations apart: a run with three calibrations is three values in three
series (one per calibration and lot, named), counted as one run; a magnitude's control limits
never go below zero (issue 33)."""

from __future__ import annotations

import math
from pathlib import Path

import psycopg
import pytest

from bench.labfixture import PgServer
from rig.lab.queries import control_limits, trend
from rig.lab.sync import run_folders, sync_runs
from rig.store import new_run

from .test_lab_index import fresh_db

pytestmark = pytest.mark.services

SOURCES = {"vector calibration": 20.0, "scalar calibration": 35.0, "with telemetry": 18.0}


def _runs(runs_dir: Path, n: int) -> None:
    for i in range(n):
        w = new_run(runs_dir, f"SN-1-{i}", procedure="DUT acceptance", parameters={},
                    dut_serial="SN-1", magnetometers=["reference", "dut"], loads=[])  # fmt: skip
        w.add_sample(0.0, "dut", (1.0, 2.0, 3.0))
        for source, rms in SOURCES.items():
            w.set_result(source, {"model": "vector", "springmann": {"x0_ut": 1.5},
                                  "residual_rms_nt": rms * (1.0 + 0.1 * (i % 3))})  # fmt: skip
        w.close("complete", "generated")


def test_one_series_per_calibration_counted_by_run(pg: PgServer, tmp_path: Path) -> None:
    url = fresh_db(pg, "trend_series")
    _runs(tmp_path / "runs", 4)
    report = sync_runs(url, run_folders(tmp_path / "runs"))
    assert len(report.added) == 4, report
    with psycopg.connect(url) as conn:
        tr = trend(conn, "residual_rms_nt")
    assert tr.runs == 4 and len(tr.rows) == 12
    assert sorted(tr.series) == sorted(f"{s}, no lot" for s in SOURCES)
    assert {row["source"] for row in tr.rows} == set(SOURCES)
    for name, lim in tr.limits.items():  # each series' limits from its own values only
        base = SOURCES[lim["source"]]
        assert name.startswith(lim["source"]) and lim["n"] == 4
        assert base <= lim["mean"] <= 1.2 * base
        assert 0.0 < lim["lcl"] < lim["mean"] < lim["ucl"]
    assert not any(row["outlier"] for row in tr.rows)


def test_a_magnitude_s_lower_limit_is_never_negative() -> None:
    rms = [22.0, 25.0, 990.0, 1419.0, 21.0]
    plain = control_limits(rms, positive=False)
    assert plain["lcl"] < 0  # what a mean +- 3 sd gives a residual
    lim = control_limits(rms, positive=True)
    logs = [math.log(v) for v in rms]
    m = sum(logs) / len(logs)
    assert lim["lcl"] > 0 and lim["ucl"] > max(rms) / 10
    assert math.log(lim["lcl"]) + math.log(lim["ucl"]) == pytest.approx(2 * m)
    assert control_limits([-1.0, 1.0, 0.5], positive=False)["lcl"] < 0  # signed values stay signed
