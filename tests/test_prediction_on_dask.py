"""The prediction against whole simulated runs on a real Dask cluster (issue 36): several worker
processes, each run on a simulated cage of its own through the wire protocols; the earlier runs'
residuals are the noise floor, the later runs' reported sigmas are what the prediction said. Few
runs here (the bench, bench/bench_prediction.py, does 200): loose bounds on each ratio."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.montecarlo

PROCEDURE = """\
procedure: Short calibration
magnetometers: {dut: dut, reference: reference}
loads: [load_bus]
steps:
  - characterize_cage: {amplitude_a: 1.0, samples: 10, repeats: 1}
    name: cage model
  - sphere_sweep: {directions: 24, magnitude_ut: [15, 45], dwell_s: 0.8, seed: 3}
    name: sweep
    loads:
      load_bus: {steps: {levels_a: [0.0, 0.8, 1.6], dwell_s: 2.4}}
  - calibrate: {model: vector, telemetry: [load_bus], steps: [sweep]}
    name: fit
"""


def test_predicted_sigmas_are_the_runs_sigmas_on_a_dask_cluster(tmp_path: Path) -> None:
    from distributed import Client

    from bench.bench_prediction import one_run, predicted, table
    from bench.dask_runs import local_cluster

    path = tmp_path / "short.yaml"
    path.write_text(PROCEDURE)
    with local_cluster(3) as cluster, Client(cluster) as client:
        assert len(client.scheduler_info()["workers"]) == 3  # a real cluster of processes
        futures = client.map(one_run, range(6), [str(path)] * 6, pure=False)
        results = client.gather(futures)
    assert not [r for r in results if "failed" in r], results
    prediction = predicted(str(path), results[:3])
    assert "the residuals of 3 earlier runs" in prediction.noise.source
    rows = table(prediction, results[3:])
    assert len(rows) == 9 + 3 + 3  # Springmann, k of load_bus, mounting
    ratio = np.array([r["ratio"] for r in rows])
    combined = np.array([r["ratio_combined"] for r in rows])
    # three runs judged on three runs' noise: a run's noise floor varies by 20-30 % (z residuals
    # of 20 and 34 nT in two demo runs), so each ratio scatters by about that much; one came to
    # 1.36 on a loaded machine. Each within 0.65-1.5, their median within 0.8-1.25.
    assert np.all((ratio > 0.65) & (ratio < 1.5)), {r["parameter"]: r["ratio"] for r in rows}
    assert np.all((combined > 0.65) & (combined < 1.5)), combined
    assert 0.8 < float(np.median(combined)) < 1.25, combined
