"""Sines on a busy computer, tried deterministically on simulated time (timebase.busy_host: the
rig's threads wake 2 ms late on average, the instruments keep time): the frequency response's
set-points slip behind their plan, and every point is then either within 3 sigma of the truth or
marked not judged, the result asking for a re-run (issue 54: at a load of 35 one axis read
1.2455 +- 0.0243 against 0.998, silently). On the same seed idle, nothing is flagged."""

from __future__ import annotations

import cmath
import math
from pathlib import Path

import pytest

import timebase
from sim.sensor_response import SensorResponse
from tests.engine.test_frequency_response_on_sim import DUT_TAU_S, config
from tests.simrun import run_on_sim

PROCEDURE = """
procedure: sines on a busy host
magnetometers: {dut: dut, reference: reference}
steps:
  - sphere_sweep: {directions: 36, magnitude_ut: [20, 45], dwell_s: 0.8, seed: 3}
    name: sweep
  - calibrate: {model: vector, steps: [sweep]}
    name: vector calibration
  - frequency_response: {frequencies_hz: [0.5, 1, 2, 4], cycles: 3, min_s: 4, rate_hz: 40,
                         amplitude_ut: 7, bias_ut: 30, axes: xy}
    name: bode
"""


def _z(point: dict[str, float]) -> tuple[float, float]:
    want = SensorResponse(DUT_TAU_S, 0.0).transfer(point["f_hz"])
    return ((point["amplitude"] - abs(want)) / point["amplitude_sigma"],
            (point["phase_deg"] - math.degrees(cmath.phase(want))) / point["phase_sigma_deg"])  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("late_s", [0.0, 0.002])
def test_every_point_is_within_3_sigma_or_not_judged(tmp_path: Path, late_s: float) -> None:
    busy = timebase.BusyHost(late_s, seed=0) if late_s else None
    outcome = run_on_sim(tmp_path, PROCEDURE, sim_config=config(), busy=busy)
    assert outcome.status == "complete", outcome.reason
    r = outcome.results["bode"]
    points = [p for ps in r["axes"].values() for p in ps]
    judged = [p for p in points if "not_judged" not in p]
    for p in judged:
        za, zp = _z(p)
        assert abs(za) < 3 and abs(zp) < 3, p
    if late_s:
        assert len(judged) < len(points) and "timing_fault" in r
        # what was not judged was worth not judging: the worst of them beyond 3 sigma
        assert max(max(map(abs, _z(p))) for p in points if p not in judged) > 3
    else:
        assert {p["f_hz"] for p in points if "not_judged" in p} <= {4.0}  # slew-limited at 4 Hz
