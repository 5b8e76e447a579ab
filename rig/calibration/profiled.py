"""Parameters found by profile likelihood: telemetry delays and the temperature scale coefficient.

The delays ``tau_j`` of the measurement model ``m = T h + o + sum_j k_j u_j(t - tau_j)``.

A channel's current reaches the DUT's reading later (or earlier) than its telemetry says: a filter
in the current sensor, the telemetry bus sampling at its own time. With sample times, ``tau_j`` is
found by profile likelihood: for a trial delay the channel's column is shifted (its own series
interpolated linearly at ``t - tau``, held at the ends) and the batch estimator refits everything
else; the weighted residual sum of squares is scanned on a grid over ``+-max_delay_s`` and refined
by bounded Brent around the best grid point, channel by channel, in sweeps until the delays settle.

Uncertainty: the Fisher information of the whole model with the delays appended - the batch
estimator's own residual Jacobian for the other parameters, and central differences for the delay
columns (``k_j du_j/dt`` at ``t - tau_j``) - so sigma and the Cramer-Rao bound include the
correlation of ``tau_j`` with ``k_j``; a sandwich of the per-sample scores widens it where the
residuals grow with the parameter's column (the misfit of step-like currents at their steps). A
channel that never changes has no observable delay and is refused. Linear interpolation turns a
step recorded between two samples into a ramp: for step-like currents the delay is resolved to a
fraction of the telemetry's sample interval, not better (steps at the sample times: to the
interval, see ``rig.calibration.fit``). The same machinery serves any parameter that acts by transforming the samples (see
:mod:`rig.calibration.temperature`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from rig.calibration.estimate import Estimate
from rig.calibration.params import Array
from rig.calibration.residuals import (
    Samples,
    scalar_noise_gain,
    scalar_residuals,
    vector_residual_values,
    vector_residuals,
)
from rig.errors import CalibrationError

GRID_POINTS = 21
"""Trial values of the coarse scan over a parameter's range (the profile can have several minima)."""
MAX_SWEEPS = 4
SETTLED = 1e-4
"""Values that moved less than this fraction of their range in a sweep have settled."""

Refit = Callable[[Samples], Estimate]
Apply = Callable[[Samples, float], Samples]


@dataclass(frozen=True)
class Profiled:
    """A parameter found by refitting everything else at trial values: ``apply`` gives the samples
    as the model sees them at a value. ``group``/``key`` place it in the result file."""

    group: str
    key: str
    unit: str
    bounds: tuple[float, float]
    step: float
    """Central-difference step of its information column (inside the data's resolution)."""
    apply: Apply
    label: str = ""
    """Its name in the parameter table (default ``group[key]``)."""
    shown_unit: str = ""
    """The unit the table shows it in (default ``unit``), ``shown_scale`` times the value."""
    shown_scale: float = 1.0

    @property
    def table_label(self) -> str:
        """Its name in the parameter table."""
        return self.label or f"{self.group}[{self.key}]"


@dataclass(frozen=True)
class ProfileFit:
    """The profiled parameters' values with 1-sigma and Cramer-Rao 1-sigma, the estimate of every
    other parameter at those values, and the samples as the model saw them there."""

    params: tuple[Profiled, ...]
    values: Array
    sigma: Array
    crlb_sigma: Array
    estimate: Estimate
    samples: Samples
    coupling: Array | None = None
    """How every other parameter moves with the profiled ones, ``d p / d values`` (P, M), from
    the whole model's information; None: not known (the others then hold them fixed)."""
    correlation: Array | None = None
    """The profiled parameters' correlation matrix (M, M), from the same information."""
    coupled_sigma: Array | None = None
    """The profiled parameters' 1-sigma as the profile gives it (information, misfit, correlated
    residuals), before any resolution the model cannot see (:func:`with_resolution`): what moves
    the others. Within a resolution interval the data are the same whatever the value, so the
    others' estimate does not depend on where in it the truth lies."""
    others_covariance: Array | None = None
    """The other parameters' covariance (P, P) from the whole model's sandwich with each
    sample's own residuals (the profiled parameters' uncertainty included); None where it does
    not apply (correlated residuals, robust weights)."""

    def marginal_covariance(self, conditional: Array) -> Array:
        """The other parameters' covariance, their uncertainty about the profiled values
        included: :attr:`others_covariance` where the residuals are white, else ``conditional``
        (the refit's at the profiled values, correlated residuals counted) plus what the profiled
        parameters' own uncertainty moves them by: ``C + G S G^T``, ``G`` the :attr:`coupling`,
        ``S`` the profiled covariance from :attr:`coupled_sigma`."""
        if self.others_covariance is not None:
            return self.others_covariance
        if self.coupling is None or self.correlation is None or self.coupled_sigma is None:
            return conditional
        s = self.correlation * np.outer(self.coupled_sigma, self.coupled_sigma)
        return np.asarray(conditional + self.coupling @ s @ self.coupling.T)


def with_resolution(fit: ProfileFit, group: str, resolution_s: dict[str, float]) -> ProfileFit:
    """``fit`` with the sigma of each parameter of ``group`` named in ``resolution_s`` widened by
    a resolution it cannot see (s, the width of an interval the value is only known within:
    uniform, sigma width / sqrt(12), added in quadrature). A delay whose channel was commanded
    in step with the DUT's samples is known only to within the command interval, whatever the
    profile's curvature says (issue 30: an orbit replay's delays 4-6 of their sigma off)."""
    extra = np.array([resolution_s.get(p.key, 0.0) if p.group == group else 0.0
                      for p in fit.params]) / np.sqrt(12.0)  # fmt: skip
    return replace(fit, sigma=np.sqrt(fit.sigma**2 + extra**2))


def shifted(times_s: Array, u: Array, tau_s: float) -> Array:
    """``u(t - tau)`` at every sample time (linear interpolation, held at the ends)."""
    return np.asarray(np.interp(times_s - tau_s, times_s, u))


Series = Callable[[Array], Array]
"""A telemetry channel's value at any times (s)."""
FieldSeries = Callable[[Array], Array]
"""The reference field (uT, (N, 3) in the cage frame) at any times (s, (N,))."""


def delay_parameter(
    s: Samples, times_s: Array, channel: str, max_delay_s: float, series: Series | None = None
) -> Profiled:
    """The delay (s) of telemetry ``channel`` within ``+-max_delay_s``; ``series`` gives the
    channel at any time (default: its column interpolated, :func:`shifted`)."""
    t = np.asarray(times_s, float)
    if t.shape != (s.n,) or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise CalibrationError(
            "delays need the sample times in seconds, finite and increasing: check --time"
        )
    if not max_delay_s > 0:
        raise CalibrationError(f"--max-delay-s must be positive, got {max_delay_s:g}")
    if channel not in s.channels:
        raise CalibrationError(
            f"--delay names {channel}, not a --telemetry channel: add it there too"
        )
    j = s.channels.index(channel)
    recorded = s.telemetry[:, j].copy()
    if np.ptp(recorded) == 0:
        raise CalibrationError(f"--delay {channel}: the channel never changes, so its delay cannot"
                               " be seen; leave it out of --delay")  # fmt: skip

    def apply(data: Samples, tau_s: float) -> Samples:
        u = data.telemetry.copy()
        u[:, j] = shifted(t, recorded, tau_s) if series is None else series(t - tau_s)
        return Samples(data.measured_ut, data.field_magnitude_ut, u, data.channels, data.field_ut)

    # inside one sample interval: the local slope of the interpolated series
    step = 0.25 * float(np.median(np.diff(t)))
    return Profiled(
        "delay_s", channel, "s", (-max_delay_s, max_delay_s), step, apply, label=f"delay[{channel}]"
    )


def clock_offset_parameter(
    s: Samples, times_s: Array, field_at: FieldSeries, bound_s: float, step_s: float = 1e-3
) -> Profiled:
    """The offset (s, within ``+-bound_s``) between the DUT's sample dates and the reference's:
    the DUT sample dated ``t`` saw the field the reference recorded at ``t + offset``.

    Each stream is dated from its own arrivals (rig.engine.stream_clock), so their latencies can
    differ by a few ms on a busy computer; in a moving field (an orbit replay) that offset
    correlates with the load currents' delays (one ms of it moved a delay by several ms on a
    tumbling run). Fitting it with the delays carries that into their sigma (issue 30).
    ``field_at(t)``: the reference field (cage frame, uT, (N, 3)) at any times (s)."""
    t = np.asarray(times_s, float)
    if t.shape != (s.n,):
        raise CalibrationError("a clock offset needs one sample time per sample")

    def apply(data: Samples, offset_s: float) -> Samples:
        field = np.asarray(field_at(t + offset_s), float)
        magnitude = np.linalg.norm(field, axis=1)
        vector = field if data.field_ut is not None else None
        return Samples(data.measured_ut, magnitude, data.telemetry, data.channels, vector)

    return Profiled("clock_offset_s", "dut", "s", (-bound_s, bound_s), step_s, apply,
                    label="DUT vs reference dates")  # fmt: skip


def profile_fit(
    s: Samples, params: tuple[Profiled, ...], refit: Refit, *, noise_ut: float | None = None
) -> ProfileFit:
    """Values of ``params`` by profile likelihood over ``s``; ``refit`` fits every other parameter
    (the batch estimator in use); ``noise_ut`` (raw 1-sigma per axis) sets the Cramer-Rao bound,
    else the residuals do."""
    values = np.zeros(len(params))

    def samples_at(v: Array) -> Samples:
        data = s
        for prm, value in zip(params, v, strict=True):
            data = prm.apply(data, float(value))
        return data

    def cost(v: Array) -> float:
        data = samples_at(v)
        try:
            est = refit(data)
        except (CalibrationError, np.linalg.LinAlgError):
            return float("inf")
        r = weighted_residual_values(est, data)
        return float(r @ r)

    from scipy.optimize import minimize_scalar  # here: importing scipy.optimize costs 0.25 s

    for _ in range(MAX_SWEEPS):
        before = values.copy()
        for i, prm in enumerate(params):

            def cost_at(x: float, i: int = i) -> float:
                trial = values.copy()
                trial[i] = x
                return cost(trial)

            lo, hi = prm.bounds
            grid = np.linspace(lo, hi, GRID_POINTS)
            width = float(grid[1] - grid[0])
            costs = [cost_at(float(g)) for g in grid]
            best = int(np.argmin(costs))
            sol = minimize_scalar(cost_at, bounds=(max(lo, grid[best] - width),
                                  min(hi, grid[best] + width)), method="bounded",
                                  options={"xatol": 1e-6 * (hi - lo)})  # fmt: skip
            values[i] = float(sol.x) if sol.fun <= costs[best] else float(grid[best])
        spans = np.array([p.bounds[1] - p.bounds[0] for p in params])
        if np.all(np.abs(values - before) < SETTLED * spans):
            break
    data = samples_at(values)
    est = refit(data)
    sigma, crlb, coupling, correlation, others = _uncertainty(est, params, samples_at, values,
                                                              noise_ut)  # fmt: skip
    return ProfileFit(params, values, sigma, crlb, est, data, coupling, correlation, sigma, others)


def weighted_residual_values(est: Estimate, s: Samples) -> Array:
    """The residuals of :func:`weighted_residuals` without their Jacobian (the profile's cost)."""
    if est.rotation_ref is not None:
        return vector_residual_values(est.p, s, est.rotation_ref)
    return weighted_residuals(est, s)[0]


def weighted_residuals(est: Estimate, s: Samples) -> tuple[Array, Array]:
    """Residuals in units of the raw noise per axis (uT) and their Jacobian in ``est.p``: vector
    residuals as they are, scalar ones divided by their noise gain (as the ML fit weighs them)."""
    if est.rotation_ref is not None:
        return vector_residuals(est.p, s, est.rotation_ref)
    r, jac = scalar_residuals(est.p, s)
    gain = scalar_noise_gain(est.p, s)
    return r / gain, jac / gain[:, None]


def _uncertainty(
    est: Estimate,
    params: tuple[Profiled, ...],
    samples_at: Callable[[Array], Samples],
    values: Array,
    noise_ut: float | None,
) -> tuple[Array, Array, Array, Array, Array | None]:
    """1-sigma and Cramer-Rao 1-sigma of the profiled parameters from the whole model's
    information (their columns by central differences at the other parameters' estimate), and
    from the same information the others' coupling to them (P, M), their correlation (M, M) and,
    with white residuals and no robust weights, the others' covariance from the whole model's
    sandwich (:attr:`ProfileFit.others_covariance`)."""
    at = samples_at(values)
    r, jac_p = weighted_residuals(est, at)
    cols = []
    for i, prm in enumerate(params):
        up, down = values.copy(), values.copy()
        up[i] += prm.step
        down[i] -= prm.step
        r_up = weighted_residual_values(est, samples_at(up))
        r_down = weighted_residual_values(est, samples_at(down))
        cols.append((r_up - r_down) / (2.0 * prm.step))
    jac = np.column_stack([jac_p, *cols])
    try:
        inv = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        names = ", ".join(f"{p.group} {p.key}" for p in params)
        raise CalibrationError(
            f"{names}: not separable from the other parameters on these data (a delay needs its"
            " current to change while the DUT is sampled, a temperature coefficient the"
            " temperature to change)"
        ) from None
    k = jac_p.shape[1]
    sigma_hat2 = float(r @ r) / max(r.size - jac.shape[1], 1)
    crlb_scale = noise_ut**2 if noise_ut is not None else sigma_hat2
    diag = np.maximum(np.diag(inv)[k:], 0.0)
    # the whiteness test over the whole model, the profiled columns included: a delay's profile
    # is as blind to correlated residuals as any other parameter's information (ADR 0025)
    from rig.calibration.correlated import rows_noise_check

    check, info, ratio = rows_noise_check(r, jac, at.n, sigma_hat2)
    sandwich = _sample_sandwich(r, jac, at.n, inv)
    white = sigma_hat2 * np.diag(inv)
    misfit = np.sqrt(np.maximum(np.diag(sandwich) / np.maximum(white, 1e-300), 1.0))[k:]
    sigma = np.sqrt(sigma_hat2 * diag) * np.maximum(check.inflation[k:], misfit)
    others = None if check.correlated or est.sample_weights is not None else sandwich[:k, :k]
    inv_tt = inv[k:, k:]
    coupling = inv[:k, k:] @ np.linalg.pinv(inv_tt)  # regression of the others on the profiled
    sd = np.sqrt(np.maximum(np.diag(inv_tt), 1e-300))
    correlation = inv_tt / np.outer(sd, sd)
    if info is None:
        return sigma, np.sqrt(crlb_scale * diag), coupling, correlation, others
    crlb = np.maximum(np.diag(np.linalg.pinv(info))[k:], 0.0)
    return sigma, np.sqrt(crlb_scale * ratio * crlb), coupling, correlation, others


def _sample_sandwich(r: Array, jac: Array, n: int, inv: Array) -> Array:
    """The heteroskedasticity-consistent covariance ``H^-1 (sum_i s_i s_i^T) H^-1`` of the whole
    model (White 1980), ``s_i`` sample ``i``'s score over its rows (a vector fit's three axes).

    A step-like current in a CSV column is a ramp to the model, so every step leaves a misfit
    where its delay's column (and its coefficient's) is large: those residuals carry the step's
    unknown time within its sample interval. The white covariance spreads them over all samples:
    it averages the delay's share away (issue 34 audit: steps at random times gave the delay rms
    z 11) and charges the coefficients' information from the held levels with it (their sigmas
    1.4 times too wide: rms z 0.70). Each profiled sigma is at least its white one."""
    res = r.reshape(n, -1)
    scores = np.einsum("nap,na->np", jac.reshape(n, res.shape[1], -1), res)
    return np.asarray(inv @ (scores.T @ scores) @ inv)
