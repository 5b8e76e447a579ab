"""Monte Carlo audit of the reported uncertainty: does |error| / sigma behave as promised?

For a scenario (the noise's colour and tails) on the synthetic cage sweep
(:func:`rig.calibration.synthetic.cage_like`), each draw adds new noise to the same field and
currents, fits with the default vector method and returns ``(estimate - truth) / sigma`` per
parameter. Honest sigmas give an rms of 1 and about 5 % of draws beyond 1.96. Used by
``tests/test_uncertainty_audit.py`` and ``bench/bench_uncertainty_audit.py`` (ADR 0025).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.calibration.params import Array
from rig.calibration.residuals import Samples, p_from_calibration
from rig.calibration.synthetic import SyntheticCase, cage_like


@dataclass(frozen=True)
class Scenario:
    """Raw noise per axis: marginal 1-sigma ``noise_ut``; AR(1) with correlation time ``tau``
    samples (0: white); Gaussian, or Student t with ``dof`` degrees of freedom scaled to that
    sigma."""

    name: str
    tau: float = 0.0
    dof: float | None = None
    noise_ut: float = 0.05


SCENARIOS = (
    Scenario("white"),
    Scenario("AR(1) tau 1", tau=1.0),
    Scenario("AR(1) tau 3", tau=3.0),
    Scenario("AR(1) tau 10", tau=10.0),
    Scenario("AR(1) tau 30", tau=30.0),
    Scenario("Student t, 3 dof", dof=3.0),
)
"""The audit's scenarios: white, coloured at several correlation times, heavy-tailed."""


def coloured_noise(rng: np.random.Generator, shape: tuple[int, int], sc: Scenario) -> Array:
    """Noise (N, 3) uT of scenario ``sc``: innovations (Gaussian or Student t, unit variance)
    filtered by AR(1) ``x_k = rho x_(k-1) + sqrt(1 - rho^2) e_k``, ``rho = exp(-1 / tau)``."""
    if sc.dof is None:
        e = rng.standard_normal(shape)
    else:
        e = rng.standard_t(sc.dof, size=shape) / math.sqrt(sc.dof / (sc.dof - 2.0))
    if sc.tau > 0:
        rho = math.exp(-1.0 / sc.tau)
        gain = math.sqrt(1.0 - rho * rho)
        for k in range(1, shape[0]):
            e[k] = rho * e[k - 1] + gain * e[k]
    return sc.noise_ut * e


def draw_z(case: SyntheticCase, sc: Scenario, seed: int) -> tuple[tuple[str, ...], Array]:
    """Parameter names and ``(estimate - truth) / reported sigma`` of one noise draw."""
    from rig.calibration.fit import calibrate

    s = case.samples
    rng = np.random.default_rng([seed, 34])
    m = case.truth.predict(case.field_ut, s.telemetry) + coloured_noise(rng, (s.n, 3), sc)
    noisy = Samples(m, s.field_magnitude_ut, s.telemetry, s.channels, s.field_ut)
    result = calibrate(noisy, "vector")
    truth = p_from_calibration(case.truth, vector=True)
    error = result.p - truth
    # the rotation error angles refer to the fitted mounting: compare rotations, not vectors
    error[9:12] = _rotation_error(result.calibration.rotation, case.truth.rotation)
    return result.names, error / result.sigma


def _rotation_error(fitted: Array, truth: Array) -> Array:
    """Small rotation vector (rad) taking ``truth`` to ``fitted``, about the DUT axes."""
    d = fitted @ truth.T
    return np.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]]) / 2.0


def audit(sc: Scenario, draws: int, n_samples: int = 2000, seed: int = 0) -> tuple[
    tuple[str, ...], Array]:  # fmt: skip
    """Names and ``z`` (draws, P) of ``draws`` noise draws of scenario ``sc``."""
    case = cage_like(n_samples, seed=seed)
    rows = [draw_z(case, sc, k) for k in range(draws)]
    return rows[0][0], np.array([z for _, z in rows])


def summary(z: Array) -> tuple[Array, Array, Array]:
    """Per parameter: rms of ``z``, 95th percentile of ``|z|``, fraction of ``|z| > 4``."""
    return (np.sqrt(np.mean(z**2, axis=0)), np.percentile(np.abs(z), 95, axis=0),
            np.mean(np.abs(z) > 4.0, axis=0))  # fmt: skip
