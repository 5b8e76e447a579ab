"""The live_calibrate step's filter on synthetic dwells: stop on target, settling, the history."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rig.calibration.params import Calibration
from rig.calibration.synthetic import cage_like
from rig.steps.live_calibrate_run import LiveCalibration

NOISE_UT = 0.03
RATE_HZ = 20.0


def params(**over: Any) -> dict[str, Any]:
    base = {"method": "ukf", "telemetry": ["load1_a", "load2_a"], "stop_on_target": "yes",
            "targets": {"bias_nt": 8.0, "scale": 5e-4, "k_ut_per_a": 0.01}, "min_s": 2.0,
            "max_s": 200.0, "settle_s": 0.25}  # fmt: skip
    return base | over


class Feed:
    """Dwells of a cage sweep: a change (ramp) then settled samples at 20 Hz, loads stepping."""

    def __init__(self, truth: Calibration, seed: int) -> None:
        self.truth = truth
        self.rng = np.random.default_rng(seed)
        self.t = 1000.0
        self.u = np.zeros(2)
        self.u_at: list[tuple[float, np.ndarray]] = [(0.0, self.u)]

    def telemetry(self, t: float) -> np.ndarray:
        return next(u for t_u, u in reversed(self.u_at) if t_u <= t)

    def dwell(self, live: LiveCalibration, n: int = 16, glitch_ut: float = 0.0) -> None:
        """One field (and sometimes a new load level); ``glitch_ut`` corrupts the ramp samples."""
        d = self.rng.standard_normal(3)
        h = d / np.linalg.norm(d) * self.rng.uniform(15.0, 60.0)
        live.change_started(self.t)
        if self.rng.uniform() < 0.3:
            self.u = self.rng.integers(0, 4, 2).astype(float)
        self.u_at.append((self.t, self.u))
        for _ in range(6):  # samples while the coils ramp: must never reach the filter
            self.t += 1 / RATE_HZ
            live.on_reference(self.t, tuple(h * 0.5))
            live.on_dut(self.t, tuple(self.truth.predict(h * 0.5, self.u) + glitch_ut))
        live.change_ended(self.t)
        for _ in range(n):
            self.t += 1 / RATE_HZ
            m = self.truth.predict(h, self.u) + NOISE_UT * self.rng.standard_normal(3)
            live.on_reference(self.t, tuple(h))
            live.on_dut(self.t, tuple(m))


def make(feed: Feed, **over: Any) -> LiveCalibration:
    live = LiveCalibration(params(**over), NOISE_UT, feed.t, feed.telemetry, None)
    live.start()
    return live


def wait_idle(live: LiveCalibration, timeout_s: float = 120.0) -> None:
    """The filter's worker has finished with every sample fed so far."""
    assert live.wait_caught_up(timeout_s), f"the filter's worker still busy after {timeout_s:g} s"


def test_stops_on_target_with_the_truth_inside_its_sigmas(tmp_path: Path) -> None:
    truth = cage_like(10, channels=2).truth
    feed = Feed(truth, seed=3)
    live = make(feed)
    dwells = 0
    while not live.done.is_set() and dwells < 400:
        feed.dwell(live, glitch_ut=50.0)
        dwells += 1
        if dwells % 20 == 0:
            wait_idle(live)
    assert live.done.is_set(), live.status()
    assert "ok" in live.status() and "bias_nt" in live.status()
    res = live.finish(tmp_path, "live cal", feed.t)
    info = res["live"]
    assert info["targets_met"] and info["stopped"].startswith("targets met after")
    assert info["sigma_at_stop"]["bias_nt"] <= 8.0 and info["sigma_at_stop"]["scale"] <= 5e-4
    # the glitched ramp samples (50 uT off) were all rejected, or the fit would be ruined
    assert info["rejected_samples"] >= 6 * dwells
    assert res["residual_rms_nt"] < 2.0 * 1000 * NOISE_UT
    sp, sig = res["springmann"], res["sigma"]["springmann"]
    true_sp = truth.springmann
    for key, true in (("a", true_sp.a), ("b", true_sp.b), ("c", true_sp.c),
                      ("x0_ut", true_sp.x0), ("y0_ut", true_sp.y0), ("z0_ut", true_sp.z0)):  # fmt: skip
        assert abs(sp[key] - true) < 4.0 * sig[key], (key, sp[key], true, sig[key])
    k_est = np.array([res["correction"]["k_ut_per_unit"][c] for c in ("load1_a", "load2_a")])
    k_sig = np.array([res["sigma"]["k_ut_per_unit"][c] for c in ("load1_a", "load2_a")])
    assert np.all(np.abs(k_est - truth.k_ut_per_unit) < 4.0 * k_sig)
    assert 0.5 < res["filter"]["mean_nis"] < 1.6
    with (tmp_path / info["history_file"]).open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0][:3] == ["elapsed_s", "samples", "a"] and "sigma_k[load2_a].z" in rows[0]
    sigma_x0 = [float(r[rows[0].index("sigma_x0")]) for r in rows[1:]]
    assert len(rows) > 5 and sigma_x0[-1] < 0.1 * sigma_x0[0]  # the sigma converged


def test_without_stop_on_target_it_runs_to_the_end(tmp_path: Path) -> None:
    feed = Feed(cage_like(10, channels=2).truth, seed=4)
    live = make(feed, stop_on_target="no", targets={})
    for _ in range(60):
        feed.dwell(live)
    wait_idle(live)
    assert not live.done.is_set()
    res = live.finish(tmp_path, "sweep", feed.t)
    assert res["live"]["stopped"] == "ran the full 200 s (stop_on_target: no)"
    # every sample is used or rejected; the ramp and 0.25 s of settling (5 samples) are rejected
    assert res["live"]["updates"] + res["live"]["rejected_samples"] == 60 * (16 + 6)
    assert res["live"]["rejected_samples"] >= 60 * (6 + 4)


def test_too_little_data_is_a_clear_error(tmp_path: Path) -> None:
    from rig.errors import CalibrationError

    feed = Feed(cage_like(10, channels=2).truth, seed=5)
    live = make(feed, method="centered-seq")
    feed.dwell(live, n=3)
    with pytest.raises(CalibrationError, match=r"never became observable .* lengthen max_s"):
        live.finish(tmp_path, "short", feed.t)


def test_with_the_plans_forecast_it_says_when_the_targets_will_be_met(tmp_path: Path) -> None:
    """The forecast (the engine's, from the plan) beside the sigmas: an ETA in the status line,
    the forecast on the page and in the history CSV, the planned stop in the result."""
    from rig.calibration.forecast import SigmaForecast

    n = tuple(range(20, 2001, 20))
    plan = SigmaForecast(n, tuple(0.08 * k for k in n),
                         {"bias_nt": tuple(12.0 * (20 / k) ** 0.5 for k in n),
                          "scale": tuple(4e-4 * (20 / k) ** 0.5 for k in n),
                          "k_ut_per_a": tuple(0.005 * (20 / k) ** 0.5 for k in n)}, 15.0)  # fmt: skip
    feed = Feed(cage_like(10, channels=2).truth, seed=3)
    live = make(feed)
    live.set_forecast(plan)  # at 15 nT; the filter's 30 nT: every sigma doubled
    assert live.forecast is not None and live.forecast.noise_nt == pytest.approx(1000 * NOISE_UT)
    for _ in range(30):
        feed.dwell(live)
    wait_idle(live)
    assert "ETA" in live.status()
    panel = live.page_state()["panel"]
    assert set(panel["forecast"]) == {"bias_nt", "scale", "k_ut_per_a"}
    assert panel["forecast_line"].startswith("forecast: ")
    while not live.done.is_set():
        feed.dwell(live)
        wait_idle(live)
    res = live.finish(tmp_path, "live cal", feed.t)
    block = res["live"]["forecast"]
    assert block["planned_stop_updates"] == 180 and block["noise_nt"] == pytest.approx(30.0)
    with (tmp_path / res["live"]["history_file"]).open() as fh:
        rows = list(csv.DictReader(fh))
    assert {"forecast_bias_nt", "forecast_scale", "forecast_stop_updates"} <= set(rows[0])
    assert any(r["forecast_stop_updates"] not in ("", "nan") for r in rows)
    other = make(Feed(cage_like(10, channels=2).truth, seed=4))
    other.set_forecast(None, "no forecast: the plan has no field")
    assert other.page_state()["panel"]["forecast_line"] == "no forecast: the plan has no field"
    other.stop()
