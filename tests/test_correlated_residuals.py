"""Correlated residuals: the whiteness test, sigmas that hold for correlated noise (ADR 0025).

The real file's offsets are checked against a moving-block bootstrap computed here (independent of
the sandwich in rig); the statistics against statsmodels'."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rig.calibration import Samples, calibrate
from rig.calibration.batch.nonlinear import ml_fit
from rig.calibration.correlated import (
    ar_long_run_information,
    autocovariance,
    ljung_box,
    long_run_covariance,
)
from rig.calibration.residuals import scalar_residuals_only
from rig.calibration.synthetic import cage_like
from rig.cli import main

SPHERE = Path(__file__).resolve().parent / "data" / "real-magnetometer" / "space-denpa-set1.csv"


def ar1(rng: np.random.Generator, shape: tuple[int, int], rho: float, sigma: float) -> np.ndarray:
    """AR(1) noise along axis 0 with lag-1 correlation ``rho`` and marginal 1-sigma ``sigma``."""
    e = rng.standard_normal(shape) * sigma * np.sqrt(1.0 - rho**2)
    out = np.empty(shape)
    out[0] = rng.standard_normal(shape[1]) * sigma
    for k in range(1, shape[0]):
        out[k] = rho * out[k - 1] + e[k]
    return out


def test_statistics_match_statsmodels() -> None:
    from statsmodels.stats.diagnostic import acorr_ljungbox
    from statsmodels.stats.sandwich_covariance import S_hac_simple

    rng = np.random.default_rng(4)
    x = ar1(rng, (5000, 2), 0.7, 1.0)
    q, p, _ = ljung_box(x, 20)
    ref = acorr_ljungbox(x[:, 0], lags=[20])
    assert q[0] == pytest.approx(float(ref["lb_stat"].iloc[0]), rel=1e-9)
    assert p[0] == pytest.approx(float(ref["lb_pvalue"].iloc[0]), abs=1e-12)
    scores = np.column_stack([x[:, 0], x[:, 0] * rng.standard_normal(5000), x[:, 1]])
    for b in (7, 40, 64):  # a window of b samples is Bartlett's kernel with b - 1 lags
        ours = 5000 * long_run_covariance(lambda rows: scores[rows], 5000, b)
        ref_s = S_hac_simple(scores, nlags=b - 1)  # differs by edge terms of order b / N
        assert ours == pytest.approx(ref_s, abs=0.05 * float(np.max(np.diag(ref_s))))
    assert autocovariance(x, 0)[0] == pytest.approx(np.var(x, axis=0))


def test_ar_model_sandwich_is_the_covariance_under_that_noise(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``sigma_e^2 Y^T Y`` against ``J^T Sigma J`` with the AR(2) noise's Toeplitz covariance
    written out (its autocovariances from the Yule-Walker recursion), blocks small enough that
    the filter state crosses several block boundaries."""
    import rig.calibration.correlated as correlated
    from rig.calibration import residuals

    n, phi = 1500, np.array([1.2, -0.35])  # a stationary AR(2), lag-1 r 0.89
    rng = np.random.default_rng(5)
    jac = rng.standard_normal((n, 2, 3)) + np.linspace(0.0, 2.0, n)[:, None, None]
    weights = rng.uniform(0.5, 1.0, n)
    gamma = np.zeros(n)  # autocovariances for unit innovations
    r1 = phi[0] / (1.0 - phi[1])
    gamma[0] = 1.0 / (1.0 - phi[0] * r1 - phi[1] * (phi[0] * r1 + phi[1]))
    gamma[1] = r1 * gamma[0]
    for k in range(2, n):
        gamma[k] = phi[0] * gamma[k - 1] + phi[1] * gamma[k - 2]
    sigma = gamma[np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])]
    wj = jac * weights[:, None, None]
    dense = sum(wj[:, a].T @ sigma @ wj[:, a] for a in range(2))
    monkeypatch.setattr(correlated, "row_blocks", lambda m: residuals.row_blocks(m, rows=97))
    ours = ar_long_run_information(lambda rows: jac[rows], n, phi, weights)
    # equal up to the start of the backward recursion (the last samples' predecessors unknown)
    assert ours == pytest.approx(dense, rel=0.01)


def test_the_real_file_reports_bootstrap_sized_offset_sigmas(tmp_path: Path) -> None:
    out = tmp_path / "r.json"
    args = [str(SPHERE), "--measured", "x,y,z", "--unit", "G", "--field-magnitude", "0.47"]
    assert main(["-q", "calibrate", *args, "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    white = result["residual_whiteness"]
    assert white["correlated"] and white["lag1_autocorrelation"] > 0.9
    assert white["heavy_tailed"] and white["inflation"]["min"] > 2.0
    assert any(w.startswith("residuals correlated") for w in result["warnings"])
    assert any("--robust" in w for w in result["warnings"])
    sm = result["sigma"]["springmann"]
    reported = np.array([sm["x0_ut"], sm["y0_ut"], sm["z0_ut"]])

    # Moving-block bootstrap of the rows, the block twice the lag at which the residuals'
    # autocorrelation falls below 1/e; 200 resamples of the maximum-likelihood fit.
    m = 100.0 * np.loadtxt(SPHERE, delimiter=",", skiprows=1)
    n = len(m)
    mag = np.full(n, 47.0)
    est = ml_fit(Samples.build(m, field_magnitude_ut=mag))
    r = scalar_residuals_only(est.p, Samples.build(m, field_magnitude_ut=mag))
    r -= r.mean()
    acf = np.array([r[: n - k] @ r[k:] for k in range(300)]) / (r @ r)
    block = 2 * int(np.argmax(acf < np.exp(-1.0)))
    assert 60 <= block <= 200
    rng = np.random.default_rng(7)
    draws = []
    for _ in range(200):
        starts = rng.integers(0, n - block + 1, size=n // block + 1)
        idx = (starts[:, None] + np.arange(block)).reshape(-1)[:n]
        draws.append(ml_fit(Samples.build(m[idx], field_magnitude_ut=mag[idx]), start=est.p).p)
    bootstrap = np.std(draws, axis=0)[3:6]
    assert reported == pytest.approx(bootstrap, rel=0.3), (reported, bootstrap)


def test_white_noise_keeps_its_sigmas() -> None:
    case = cage_like(2000, seed=11)
    result = calibrate(case.samples, "vector", noise_nt=50.0)
    assert result.noise_check is not None and not result.noise_check.correlated
    assert np.all(result.noise_check.inflation == 1.0)
    assert result.crlb_ratio == pytest.approx(np.ones(result.p.size), abs=0.05)
    assert not any("correlated" in w or "heavy" in w for w in result.warnings)
    assert result.to_dict()["residual_whiteness"]["sigma_method"] == "white-noise least squares"


def test_coloured_noise_is_named_and_inflates_the_offsets() -> None:
    case = cage_like(3000, seed=12)
    s = case.samples
    rng = np.random.default_rng(1)
    noisy = Samples(case.truth.predict(case.field_ut, s.telemetry)
                    + ar1(rng, (s.n, 3), 0.8, 0.05), s.field_magnitude_ut, s.telemetry,
                    s.channels, s.field_ut)  # fmt: skip
    result = calibrate(noisy, "vector")
    check = result.noise_check
    assert check is not None and check.correlated and check.lag1 == pytest.approx(0.8, abs=0.05)
    offsets = [result.names.index(k) for k in ("x0", "y0", "z0")]
    # long-run / marginal sigma of AR(1) 0.8: sqrt((1 + 0.8) / (1 - 0.8)) = 3
    assert check.inflation[offsets] == pytest.approx(3.0, rel=0.25)
    assert check.ar_order >= 1 and result.crlb_ratio[offsets] == pytest.approx(1.0, abs=0.3)


def test_heavy_tails_point_to_robust() -> None:
    case = cage_like(3000, seed=13)
    s = case.samples
    noise = 0.05 * np.random.default_rng(2).standard_t(3, size=(s.n, 3)) / np.sqrt(3.0)
    noisy = Samples(case.truth.predict(case.field_ut, s.telemetry) + noise,
                    s.field_magnitude_ut, s.telemetry, s.channels, s.field_ut)  # fmt: skip
    result = calibrate(noisy, "vector")
    assert any("heavy-tailed" in w and "--robust huber" in w for w in result.warnings)
    robust = calibrate(noisy, "vector", robust="huber")
    assert not any("--robust huber" in w for w in robust.warnings)
