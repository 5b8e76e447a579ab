"""When a live calibration will meet its targets: the plan's forecast carried forward by the
run's own sigmas (issue 36), and the forecast being the filter's own covariance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig.calibration.forecast import SigmaForecast, forecast_stop
from rig.calibration.residuals import Samples
from rig.calibration.synthetic import cage_like
from rig.calibration.targets import group_sigmas
from rig.prediction.live_calibrate_stop import filter_forecast


def falling(noise_nt: float = 20.0) -> SigmaForecast:
    """A forecast falling as 1/sqrt(updates): bias 100 nT after 10 updates."""
    n = tuple(range(10, 1001, 10))
    return SigmaForecast(n, tuple(0.1 * k for k in n),
                         {"bias_nt": tuple(100.0 * math.sqrt(10 / k) for k in n),
                          "scale": tuple(1e-2 * math.sqrt(10 / k) for k in n)}, noise_nt)  # fmt: skip


def test_the_forecast_scales_with_the_noise_and_falls_between_and_beyond_its_rows() -> None:
    f = falling()
    assert f.at(40)["bias_nt"] == pytest.approx(50.0)
    assert f.at(45)["bias_nt"] == pytest.approx(100.0 * math.sqrt(10 / 45), rel=1e-9)  # log-log
    assert f.at(4000)["bias_nt"] == pytest.approx(100.0 * math.sqrt(10 / 4000))
    assert f.scaled(40.0).at(40)["bias_nt"] == pytest.approx(100.0)
    assert f.first_met({"bias_nt": 20.0, "scale": 0.01}) == 250
    assert f.dwell_at(250) == pytest.approx(25.0)


def test_a_run_twice_as_noisy_as_planned_is_forecast_to_take_four_times_the_samples() -> None:
    f = falling()
    # after 100 updates in 20 s the run's bias sigma is twice the plan's, its scale as planned
    now = {"bias_nt": 2 * f.at(100)["bias_nt"], "scale": f.at(100)["scale"]}
    stop = forecast_stop(f, now, 100, 20.0, {"bias_nt": 20.0, "scale": 0.01})
    assert stop.ratios["bias_nt"] == pytest.approx(2.0) and stop.ratios["scale"] == pytest.approx(1)
    assert stop.updates == 1000  # (2 x 100 / 20)^2 x 10
    assert stop.eta_s == pytest.approx((1000 - 100) / 5.0)  # at this run's 5 updates a second
    assert "targets met in about 180 s" in stop.line()
    never = forecast_stop(f, now, 100, 20.0, {"bias_nt": 5.0, "scale": 0.01})
    assert never.updates is None and never.limiting == "bias_nt" and "not met" in never.line()
    met = forecast_stop(
        f, {"bias_nt": 1.0, "scale": 1e-4}, 100, 20.0, {"bias_nt": 20.0, "scale": 0.01}
    )
    assert met.updates == 100 and met.eta_s == 0.0


def test_the_forecast_is_the_filters_own_covariance_at_every_row() -> None:
    """The forecast's sigmas are the ones the same filter reports on the same samples (the run's
    live view computes them from the filter's covariance the same way)."""
    from rig.calibration.fit import calibrate

    case = cage_like(300, channels=1, seed=5)
    truth = case.truth
    rng = np.random.default_rng(1)
    h, u = case.samples.field_ut, case.samples.telemetry
    m = truth.predict(h, u) + 0.02 * rng.standard_normal(h.shape)
    s = Samples.build(m, field_ut=h, telemetry=u, channels=case.samples.channels)
    t = np.arange(s.n) / 20.0
    f = filter_forecast(s, t, "ukf", 20.0)
    assert f.updates[-1] == s.n and len(f.updates) >= 50
    for n in (f.updates[len(f.updates) // 2], f.updates[-1]):
        fit = calibrate(s.head(n), "ukf", noise_nt=20.0)
        own = group_sigmas(fit.sigma, fit.names)
        for group, sigma in own.items():
            assert f.sigmas[group][f.updates.index(n)] == pytest.approx(sigma, rel=0.01), group
