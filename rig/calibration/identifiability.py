"""Is a scalar (attitude-independent) calibration identifiable on this data? Decided from the
Fisher information of the maximum-likelihood problem, not from a count of samples in cones
(docs/adr/0026-identifiability-by-information.md).

The parameters are scaled to a common size before asking: scale factors as they are (1 = 100 %),
offsets by the mean field magnitude (uT), angles by 1 rad, each current-to-bias coefficient by the
mean field magnitude over its channel's standard deviation (uT per channel unit). A combination of
the scaled parameters is not determined when

* the maximum-likelihood fit from the linear start runs off (no finite maximum; the combination
  is the direction it runs along), or
* its 1-sigma from the information exceeds 1 (a scale combination not known to 100 %, an offset
  combination with a sigma above the field magnitude), or
* the scaled information is singular to working precision.

Then the fit is refused, naming the combination; otherwise a missing field direction only costs
precision, and the warning says how much (sigmas with hypothetical samples in the missing caps).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rig.calibration.diagnostics import (
    CAPS,
    COVERAGE_CONE_DEG,
    COVERAGE_MIN_FRACTION,
    coverage_text,
    direction_coverage,
)
from rig.calibration.estimate import Estimate
from rig.calibration.params import Array
from rig.calibration.residuals import (
    Samples,
    calibration_from_p,
    parameter_names,
    scalar_noise_gain,
    scalar_normal_equations,
)
from rig.calibration.solver import levenberg_marquardt
from rig.errors import CalibrationError

RELATIVE_SIGMA_LIMIT = 1.0
"""A scaled combination with a larger 1-sigma (relative; 1 = its own size) is not determined."""
SINGULAR_RCOND = 1e3 * float(np.finfo(float).eps)
"""Smallest over largest eigenvalue of the scaled information below which it is singular."""
CHECK_ROWS = 20_000
"""The check fits on at most about this many evenly spread rows; the information is scaled up to
all samples (it grows in proportion to their number)."""
CAP_SHARE = 0.25
"""Hypothetical samples per missing cap, as a fraction of the sample count: a uniform sweep of
the same length puts 1 - cos(60 deg) over 2 = 25 % of its samples within 60 deg of each axis."""
BIAS_REPORTED = 1.0
"""A parameter's predicted noise bias is named in a warning when it reaches this many sigmas."""
BIAS_REFUSED = 3.0
"""... and the fit is refused when it reaches this many: the estimate would sit further from the
truth than its sigma could cover (a cap within 60 deg of -z at 0.2 uT: z0 about 19 sigma off)."""
SHRINK_REPORTED = 1.5
"""A parameter's sigma is named in the warning when the missing caps would shrink it this much."""
WORDS = {"a": "x scale", "b": "y scale", "c": "z scale", "x0": "x0 offset", "y0": "y0 offset",
         "z0": "z0 offset", "rho": "rho angle", "phi": "phi angle", "lambda": "lambda angle"}  # fmt: skip


@dataclass(frozen=True)
class Information:
    """The scalar ML problem at ``p``: its Fisher information (P, P; inverse units of ``p``
    squared, for all samples), the raw noise it assumed (uT) and whether the fit converged."""

    p: Array
    fisher: Array
    noise_ut: float
    converged: bool


def parameter_scales(s: Samples) -> Array:
    """Size of each scalar-model parameter: 1 for scales and angles (rad), mean |h| (uT) for
    offsets, mean |h| / std(u_j) (uT per unit) for the coefficients of channel j."""
    field = float(np.mean(s.field_magnitude_ut))
    spread = np.maximum(np.std(s.telemetry, axis=0), 1e-300)
    return np.concatenate([np.ones(3), np.full(3, field), np.ones(3), np.repeat(field / spread, 3)])


def _check_rows(s: Samples) -> Samples:
    """At most about :data:`CHECK_ROWS` evenly spread rows of ``s``."""
    return s if s.n <= 2 * CHECK_ROWS else s.rows(slice(0, s.n, s.n // CHECK_ROWS))


def information(s: Samples, start: Array) -> Information:
    """Fit the scalar ML problem from ``start`` (weights fixed at the start's noise gains) on at
    most :data:`CHECK_ROWS` rows and return its information at the point reached."""
    sub = _check_rows(s)
    w = 1.0 / scalar_noise_gain(start, sub) ** 2
    sol = levenberg_marquardt(lambda x: scalar_normal_equations(x, sub, w), start)
    return _information_at(s, sol.x, sol.converged)


def converging_start(s: Samples, start: Array | None) -> tuple[Array, Information] | None:
    """``start`` when the scalar ML fit converges from it, else the nominal sensor (unit scales,
    no offset, angles or coefficients) when the fit converges from there, else ``start`` (None:
    no linear start could be had); with the fit's :func:`information` from the one returned. A
    linear start on few distinct fields can be far off: 19 held fields with two load channels
    gave scales 1.9-5.6 and a 181 uT offset, and the fit ran off from it (issue 55)."""
    info = None if start is None else information(s, start)
    if start is not None and info is not None and info.converged:
        return start, info
    nominal = np.zeros(9 + 3 * s.n_channels)
    nominal[:3] = 1.0
    from_nominal = information(s, nominal)
    if from_nominal.converged:
        return nominal, from_nominal
    return None if start is None or info is None else (start, info)


def _information_at(s: Samples, p: Array, converged: bool) -> Information:
    """The scalar ML problem's information at ``p`` over all of ``s`` (from at most
    :data:`CHECK_ROWS` rows), the noise from the residuals there."""
    sub = _check_rows(s)
    normal = scalar_normal_equations(p, sub, noise_weighted=True)
    floor = 1e-9 * float(np.mean(sub.field_magnitude_ut))  # noise-free data: no division by 0
    noise2 = max(normal.cost / max(sub.n - p.size, 1), floor**2)
    fisher = normal.jtj / noise2 * (s.n / sub.n)
    return Information(p, fisher, float(np.sqrt(noise2)), converged)


def worst_combination(fisher: Array, scales: Array) -> tuple[float, Array]:
    """1-sigma of the least determined combination of the scaled parameters (inf when the
    information is singular) and that combination (unit vector over the scaled parameters)."""
    eig, vec = np.linalg.eigh(scales[:, None] * fisher * scales[None, :])
    if not eig[0] > SINGULAR_RCOND * eig[-1]:
        return float("inf"), vec[:, 0]
    return float(1.0 / np.sqrt(eig[0])), vec[:, 0]


def combination_words(direction: Array, names: tuple[str, ...]) -> str:
    """'z scale and z0 offset trade off' for the parameters carrying a combination (those with
    at least 30 % of its largest component), in parameter order."""
    size = np.abs(direction)
    involved = [WORDS.get(name, f"{name} coefficient") for name, x in zip(names, size, strict=True)
                if x >= 0.3 * size.max()]  # fmt: skip
    if len(involved) == 1:
        return f"{involved[0]} is not determined"
    return f"{', '.join(involved[:-1])} and {involved[-1]} trade off"


def missing_caps(coverage: dict[str, float]) -> list[str]:
    """Axis directions (+x, ...) with under :data:`COVERAGE_MIN_FRACTION` of the samples."""
    return [c for c in CAPS if coverage[c] < COVERAGE_MIN_FRACTION]


def check_identifiable(
    s: Samples,
    start: Array,
    method: str,
    bias_handled: bool = False,
    info: Information | None = None,
) -> tuple[str, ...]:
    """Raise CalibrationError (one line) when a combination of the scalar parameters is not
    determined by ``s``; else, when field directions are missing, warnings: what recording them
    would do to the sigmas, and the noise bias when it reaches a sigma (none on a full sphere)
    and the fit will neither remove it nor carry it in its sigmas (``bias_handled``)."""
    info = information(s, start) if info is None else info
    scales = parameter_scales(s)
    names = parameter_names(s.channels, vector=False)
    rel_sigma, direction = worst_combination(info.fisher, scales)
    # about the start's offset, unless the fit ran off from a start whose offset is larger than
    # the readings (a 181 uT one had made every sample point at -z): then about none
    wild = float(np.linalg.norm(start[3:6])) > float(
        np.median(np.linalg.norm(s.measured_ut, axis=1))
    )
    centre = np.zeros(3) if wild and not info.converged else start[3:6]
    coverage = direction_coverage(s.measured_ut, centre)
    missing = missing_caps(coverage)
    if not info.converged:  # the likelihood has no finite maximum: name where the fit ran
        run = (info.p - start) / scales
        direction = run / max(float(np.linalg.norm(run)), 1e-300)
    if info.converged and rel_sigma <= RELATIVE_SIGMA_LIMIT:
        if not missing:
            return ()
        bias = bias_warning(s, info, ", ".join(missing), method, bias_handled)
        return (coverage_warning(s, info, coverage, missing),) + ((bias,) if bias else ())
    why = "the fit runs off along it" if not info.converged else _sigma_words(rel_sigma)
    fix = f"record directions with {', '.join(missing)}" if missing else "record more directions"
    raise CalibrationError(
        f"{combination_words(direction, names)}: a scalar ({method}) fit cannot determine that"
        f" combination on this data ({why}; field directions: {coverage_text(coverage)}); {fix}"
        " (turn the sensor through every attitude), or calibrate against a field vector (--field)"
    )


def _sigma_words(rel_sigma: float) -> str:
    if not np.isfinite(rel_sigma):
        return "its information is zero to working precision"
    return f"its 1-sigma is {rel_sigma:.3g} times its own size"


def hypothetical_samples(s: Samples, p: Array, caps: list[str], count: int) -> Samples:
    """``count`` noise-free samples per cap in ``caps``: raw directions (about the offset) spread
    evenly within :data:`COVERAGE_CONE_DEG` of the axis direction, at the mean field magnitude,
    the telemetry at its mean, on the model ``p``."""
    cal = calibration_from_p(p, s.channels)
    field = float(np.mean(s.field_magnitude_ut))
    # An even spiral over the cone: heights uniform in cos(angle), golden-angle azimuths.
    k = np.arange(count) + 0.5
    cos_t = 1.0 - (1.0 - np.cos(np.radians(COVERAGE_CONE_DEG))) * k / count
    sin_t, phi = np.sqrt(1.0 - cos_t**2), np.pi * (3.0 - np.sqrt(5.0)) * k
    local = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
    w = np.linalg.inv(cal.t_matrix)
    u_mean = np.mean(s.telemetry, axis=0)
    rows = []
    for cap in caps:
        axis = "xyz".index(cap[1])
        raw = np.roll(local, axis + 1, axis=1) * (1.0 if cap[0] == "+" else -1.0)
        h = raw @ w.T
        h *= field / np.linalg.norm(h, axis=1, keepdims=True)
        rows.append(cal.predict(h, np.tile(u_mean, (count, 1))))
    m = np.vstack(rows)
    u = np.tile(u_mean, (m.shape[0], 1))
    return Samples.build(m, field_magnitude_ut=np.full(m.shape[0], field), telemetry=u,
                         channels=s.channels)  # fmt: skip


def coverage_warning(
    s: Samples, info: Information, coverage: dict[str, float], missing: list[str]
) -> str:
    """The weakly covered directions and, per parameter whose sigma the missing caps would
    shrink by :data:`SHRINK_REPORTED` or more, its sigma now and with them recorded."""
    count = max(int(CAP_SHARE * s.n), 50)
    extra = hypothetical_samples(s, info.p, missing, count)
    added = scalar_normal_equations(info.p, extra, noise_weighted=True).jtj / info.noise_ut**2
    now = np.sqrt(np.diag(np.linalg.inv(info.fisher)))
    then = np.sqrt(np.diag(np.linalg.inv(info.fisher + added)))
    names = parameter_names(s.channels, vector=False)
    caps = ", ".join(missing)
    gains = [_sigma_pair(names[i], now[i], then[i], caps) for i in range(now.size)
             if now[i] >= SHRINK_REPORTED * then[i]]  # fmt: skip
    tail = (
        "; ".join(gains)
        if gains
        else f"no sigma would shrink {SHRINK_REPORTED:g}x with {caps} recorded"
    )
    return (
        f"field directions: {coverage_text(coverage)}; the calibration is identifiable but"
        f" weaker for it: {tail} ({count} noise-free samples per missing direction)"
    )


def noise_bias(s: Samples, info: Information) -> Array:
    """Expected shift (units of ``p``) of the scalar ML estimate caused by the raw noise itself.

    The fit weighs each residual by ``1/g_k^2`` with the noise gain ``g_k = |W^T n_k|`` taken as
    fixed, and its Jacobian and gains hold the noisy reading: the expected score (normal equations
    ``J^T J / sigma^2``) at the truth is then ``sum_k d log g_k / dp`` (the derivative of the
    log-likelihood's ``log g_k`` term the fit leaves out), and the estimate moves by ``-F^-1``
    times it (``F`` the Fisher information). It cancels over a sphere
    of directions, not over one side of it (0.085 uT predicted on z0 of a hemisphere at 0.2 uT,
    0.071 uT found; docs/adr/0026).
    """
    sub = _check_rows(s)
    score = np.zeros(info.p.size)
    for i in range(info.p.size):
        step = np.zeros(info.p.size)
        step[i] = 1e-6 * max(abs(float(info.p[i])), 1.0)
        up, down = scalar_noise_gain(info.p + step, sub), scalar_noise_gain(info.p - step, sub)
        score[i] = np.sum(np.log(up / down)) / (2.0 * step[i])
    # The score sigma^2 sum d log g / dp over F = J^T J / sigma^2 (both for all samples).
    return np.asarray(-np.linalg.solve(info.fisher, score * (s.n / sub.n)))


def without_noise_bias(est: Estimate, s: Samples) -> Estimate:
    """``est``, a scalar ML estimate of the one-sided samples ``s``, with its
    :func:`noise_bias` at the estimate subtracted (a first-order correction: on the audit's TRMM
    orbit and hemisphere it takes the mean error from +1 to +2 sigma to within 0.1 sigma) and a
    note naming the largest shift in sigmas."""
    bias, largest = _bias_at_estimate(est, s, shift=True)
    note = ("the raw noise's bias on one-sided field directions is removed from the estimate"
            f" (largest shift {largest}; docs/adr/0026)")  # fmt: skip
    return replace(est, p=est.p - bias, notes=(*est.notes, note))


def with_noise_bias_in_sigmas(est: Estimate, s: Samples) -> Estimate:
    """``est``, a scalar estimate of the one-sided samples ``s`` by a method that does not remove
    its :func:`noise_bias` (a filter, a two-step fit), with that bias carried in its covariance
    (``+ b b^T``: the sigmas become root mean squared errors) and a note naming the largest one
    in sigmas and the method that removes it instead (issue 54: the filters' sigmas had been 5-20
    % optimistic on one-sided orbits)."""
    bias, largest = _bias_at_estimate(est, s, shift=False)
    note = ("the raw noise's bias on one-sided field directions is carried in the sigmas as a mean"
            f" squared error (largest {largest}); --method ml removes it from the estimate instead"
            " (docs/adr/0026)")  # fmt: skip
    return replace(est, covariance=est.covariance + np.outer(bias, bias), notes=(*est.notes, note))


def _bias_at_estimate(est: Estimate, s: Samples, shift: bool) -> tuple[Array, str]:
    """:func:`noise_bias` at ``est``, and its largest part in sigmas as words ('z0 -0.084 uT,
    2.0 sigma'; as the shift that removes it with ``shift``)."""
    bias = noise_bias(s, _information_at(s, est.p, True))
    sigma = np.sqrt(np.maximum(np.diag(est.covariance), 1e-300))
    worst = int(np.argmax(np.abs(bias) / sigma))
    name = parameter_names(s.channels, vector=False)[worst]
    value = _value(name, -bias[worst] if shift else bias[worst], signed=True)
    return bias, f"{value}, {abs(bias[worst]) / sigma[worst]:.1f} sigma"


NOISE_BIAS_REMOVED = frozenset({"ml"})
"""Scalar methods whose estimate on one-sided data has :func:`noise_bias` removed
(:func:`without_noise_bias`; without a robust loss, whose weights the bias does not model)."""


def bias_warning(
    s: Samples, info: Information, caps: str, method: str = "ml", handled: bool = False
) -> str | None:
    """The parameters whose :func:`noise_bias` reaches :data:`BIAS_REPORTED` of their sigma
    (None when the fit will remove it or carry it in its sigmas, ``handled``); CalibrationError when one reaches
    :data:`BIAS_REFUSED`: beyond what a first-order correction or a sigma can promise."""
    bias = noise_bias(s, info)
    sigma = np.sqrt(np.diag(np.linalg.inv(info.fisher)))
    names = parameter_names(s.channels, vector=False)
    large = [f"{_value(names[i], bias[i], signed=True)} ({bias[i] / sigma[i]:+.1f} sigma)"
             for i in range(bias.size) if abs(bias[i]) >= BIAS_REPORTED * sigma[i]]  # fmt: skip
    if np.any(np.abs(bias) >= BIAS_REFUSED * sigma):
        raise CalibrationError(
            f"the raw noise biases a scalar ({method}) fit on these one-sided field directions by"
            f" about {', '.join(large)}, beyond what its sigma can cover: record {caps} (turn the"
            " sensor through every attitude), or calibrate against a field vector (--field)"
        )
    if not large or handled:
        return None
    return (
        "the raw noise biases a scalar fit on one-sided field directions, here by about "
        + ", ".join(large)
        + f" (not in the sigmas; the estimate is off by that much on average): record {caps}"
    )


def _value(name: str, value: float, *, signed: bool = False) -> str:
    """'z0 +0.085 uT' in the parameter's unit."""
    unit, factor = " uT", 1.0
    if name in ("a", "b", "c"):
        unit = ""
    elif name in ("rho", "phi", "lambda"):
        unit, factor = " deg", float(np.degrees(1.0))
    elif name.startswith("k["):
        unit = " uT/unit"
    return f"{name} {factor * value:{'+' if signed else ''}.2g}{unit}"


def _sigma_pair(name: str, now: float, then: float, caps: str) -> str:
    """'x0 sigma 0.039 uT, 0.012 uT with -z recorded' in the parameter's unit."""
    before, after = (_value(name, v).split(" ", 1)[1] for v in (now, then))
    return f"{name} sigma {before}, {after} with {caps} recorded"
