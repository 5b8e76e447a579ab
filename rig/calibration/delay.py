"""Telemetry delays ``tau_j`` of the measurement model ``m = T h + o + sum_j k_j u_j(t - tau_j)``.

A channel's current reaches the DUT's reading later (or earlier) than its telemetry says: a filter
in the current sensor, the telemetry bus sampling at its own time. With sample times, ``tau_j`` is
found by profile likelihood: for a trial delay the channel's column is shifted (its own series
interpolated linearly at ``t - tau``, held at the ends) and the batch estimator refits everything
else; the weighted residual sum of squares is scanned on a grid over ``+-max_delay_s`` and refined
by bounded Brent around the best grid point, channel by channel, in sweeps until the delays settle.

Uncertainty: the Fisher information of the whole model with the delays appended - the batch
estimator's own residual Jacobian for the other parameters, and central differences for the delay
columns (``k_j du_j/dt`` at ``t - tau_j``) - so sigma and the Cramer-Rao bound include the
correlation of ``tau_j`` with ``k_j``. A channel that never changes has no observable delay and is
refused. Linear interpolation turns a step recorded between two samples into a ramp: for step-like
currents the delay is resolved to a fraction of the telemetry's sample interval, not better.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from rig.calibration.estimate import Estimate
from rig.calibration.params import Array
from rig.calibration.residuals import (
    Samples,
    scalar_noise_gain,
    scalar_residuals,
    vector_residuals,
)
from rig.errors import CalibrationError

GRID_POINTS = 21
"""Trial delays of the coarse scan over ``+-max_delay_s`` (the profile can have several minima)."""
MAX_SWEEPS = 4
SETTLED_S = 1e-4
"""Delays that moved less than this in a sweep (s) have settled."""

Refit = Callable[[Samples], Estimate]


@dataclass(frozen=True)
class DelayFit:
    """Estimated delays (s) of ``channels`` with 1-sigma and Cramer-Rao 1-sigma (s), the estimate
    of every other parameter at those delays, and the samples with the shifted telemetry."""

    channels: tuple[str, ...]
    delays_s: Array
    sigma_s: Array
    crlb_sigma_s: Array
    estimate: Estimate
    samples: Samples


def shifted(times_s: Array, u: Array, tau_s: float) -> Array:
    """``u(t - tau)`` at every sample time (linear interpolation, held at the ends)."""
    return np.asarray(np.interp(times_s - tau_s, times_s, u))


def with_delays(s: Samples, times_s: Array, index: list[int], delays_s: Array) -> Samples:
    """``s`` with telemetry columns ``index`` delayed by ``delays_s`` (s)."""
    u = s.telemetry.copy()
    for j, tau in zip(index, delays_s, strict=True):
        u[:, j] = shifted(times_s, s.telemetry[:, j], float(tau))
    return Samples(s.measured_ut, s.field_magnitude_ut, u, s.channels, s.field_ut)


def weighted_residuals(est: Estimate, s: Samples) -> tuple[Array, Array]:
    """Residuals in units of the raw noise per axis (uT) and their Jacobian in ``est.p``: vector
    residuals as they are, scalar ones divided by their noise gain (as the ML fit weighs them)."""
    if est.rotation_ref is not None:
        return vector_residuals(est.p, s, est.rotation_ref)
    r, jac = scalar_residuals(est.p, s)
    gain = scalar_noise_gain(est.p, s)
    return r / gain, jac / gain[:, None]


def _cost(refit: Refit, s: Samples, times_s: Array, index: list[int], delays: Array) -> float:
    data = with_delays(s, times_s, index, delays)
    try:
        est = refit(data)
    except (CalibrationError, np.linalg.LinAlgError):
        return float("inf")
    r, _ = weighted_residuals(est, data)
    return float(r @ r)


def estimate_delays(
    s: Samples,
    times_s: Array,
    channels: tuple[str, ...],
    refit: Refit,
    *,
    max_delay_s: float = 2.0,
    noise_ut: float | None = None,
) -> DelayFit:
    """Delays of ``channels`` (telemetry columns of ``s``) given sample ``times_s`` (s).

    ``refit`` fits every other parameter to samples with shifted telemetry (the batch estimator
    in use); ``noise_ut`` (raw 1-sigma per axis) sets the Cramer-Rao bound, else the residuals do.
    """
    t = np.asarray(times_s, float)
    if t.shape != (s.n,) or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise CalibrationError(
            "delays need the sample times in seconds, finite and increasing: check --time"
        )
    if not max_delay_s > 0:
        raise CalibrationError(f"--max-delay-s must be positive, got {max_delay_s:g}")
    unknown = [c for c in channels if c not in s.channels]
    if unknown:
        raise CalibrationError(
            f"--delay names {', '.join(unknown)}, not a --telemetry channel: add it there too"
        )
    index = [s.channels.index(c) for c in channels]
    for c, j in zip(channels, index, strict=True):
        if np.ptp(s.telemetry[:, j]) == 0:
            raise CalibrationError(f"--delay {c}: the channel never changes, so its delay cannot"
                                   " be seen; leave it out of --delay")  # fmt: skip
    delays = np.zeros(len(index))
    grid = np.linspace(-max_delay_s, max_delay_s, GRID_POINTS)
    step = float(grid[1] - grid[0])
    for _ in range(MAX_SWEEPS):
        before = delays.copy()
        for i in range(len(index)):

            def cost_at(tau: float, i: int = i) -> float:
                trial = delays.copy()
                trial[i] = tau
                return _cost(refit, s, t, index, trial)

            costs = [cost_at(float(g)) for g in grid]
            best = int(np.argmin(costs))
            lo = max(-max_delay_s, float(grid[best]) - step)
            hi = min(max_delay_s, float(grid[best]) + step)
            sol = minimize_scalar(cost_at, bounds=(lo, hi), method="bounded",
                                  options={"xatol": 1e-5})  # fmt: skip
            delays[i] = float(sol.x) if sol.fun <= costs[best] else float(grid[best])
        if np.max(np.abs(delays - before)) < SETTLED_S:
            break
    data = with_delays(s, t, index, delays)
    est = refit(data)
    sigma, crlb = _delay_uncertainty(est, s, t, index, delays, noise_ut)
    return DelayFit(tuple(channels), delays, sigma, crlb, est, data)


def _delay_uncertainty(
    est: Estimate, s: Samples, t: Array, index: list[int], delays: Array, noise_ut: float | None
) -> tuple[Array, Array]:
    """1-sigma and Cramer-Rao 1-sigma of the delays (s) from the whole model's information."""
    data = with_delays(s, t, index, delays)
    r, jac_p = weighted_residuals(est, data)
    h = 0.25 * float(np.median(np.diff(t)))  # inside one sample interval: the local slope
    cols = []
    for i in range(len(index)):
        up, down = delays.copy(), delays.copy()
        up[i] += h
        down[i] -= h
        r_up, _ = weighted_residuals(est, with_delays(s, t, index, up))
        r_down, _ = weighted_residuals(est, with_delays(s, t, index, down))
        cols.append((r_up - r_down) / (2.0 * h))
    jac = np.column_stack([jac_p, *cols])
    info = jac.T @ jac
    try:
        inv = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        raise CalibrationError(
            "the delays cannot be told from the current-to-bias coefficients on these data: the"
            " currents must change while the DUT is sampled"
        ) from None
    dof = max(r.size - jac.shape[1], 1)
    sigma_hat2 = float(r @ r) / dof
    crlb_var = (noise_ut**2 if noise_ut is not None else sigma_hat2) * np.diag(inv)
    k = jac_p.shape[1]
    return np.sqrt(np.maximum(sigma_hat2 * np.diag(inv)[k:], 0.0)), np.sqrt(
        np.maximum(crlb_var[k:], 0.0)
    )
