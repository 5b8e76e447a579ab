"""One entry point: pick an estimator from the table, run it, return a CalibrationResult."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from rig.calibration.batch.nonlinear import ml_fit
from rig.calibration.diagnostics import check_samples
from rig.calibration.estimate import Estimate
from rig.calibration.estimators import (
    DEFAULT_METHOD,
    Estimator,
    FitRequest,
    Method,
    estimator,
    method_names,
    spoken,
)
from rig.calibration.params import Array
from rig.calibration.residuals import Samples, scalar_noise_gain, scalar_residuals_only
from rig.calibration.result import CalibrationResult, summarize
from rig.calibration.robust import RobustLoss
from rig.errors import CalibrationError

if TYPE_CHECKING:
    # Imported where used: delays, temperature and the filters pull in modules (and scipy) that a
    # plain batch fit does not need.
    from rig.calibration.profiled import FieldSeries, Profiled, Series
    from rig.calibration.sequential.realtime import FilterOptions

    ClockOffset = tuple[FieldSeries, float]
    """The reference field at any time and the offset's bound (s)."""

METHODS: tuple[Method, ...] = method_names()


def default_method(s: Samples) -> Method:
    """The best estimator for the input: ``vector`` with a field vector, else ``ml``."""
    return DEFAULT_METHOD["vector" if s.field_ut is not None else "scalar"]


def _checked_estimator(
    s: Samples, method: Method | None, noise_nt: float | None, robust: RobustLoss | None
) -> Estimator:
    """The estimator for ``method`` (default: :func:`default_method`); CalibrationError (one
    line, the fix) when the options or the data do not suit it."""
    est = estimator(method or default_method(s))
    if robust is not None and not est.robust:
        raise CalibrationError(
            f"--robust works with --method {spoken(method_names(robust=True))}, not {est.name}:"
            " drop --robust or change method"
        )
    if noise_nt is not None and not noise_nt > 0:
        raise CalibrationError(f"--noise-nt must be positive, got {noise_nt:g}")
    if est.model == "vector" and s.field_ut is None:
        raise CalibrationError(
            f"--method {est.name} needs the field vector: give --field X,Y,Z instead of"
            " --field-magnitude"
        )
    return est


def _with_temperature(
    s: Samples, temperature: Array | None, temperature_ref: float | None
) -> tuple[Samples, float | None]:
    """``s`` with the temperature channel (T - T_ref, K) and T_ref (default: the mean); ``s``
    and None without a temperature."""
    if temperature is None:
        return s, None
    from rig.calibration.temperature import with_temperature_channel

    reference = float(np.mean(temperature)) if temperature_ref is None else temperature_ref
    return with_temperature_channel(s, temperature, reference), reference


def _profiled_parameters(
    data: Samples,
    times_s: Array | None,
    delays: tuple[str, ...],
    max_delay_s: float,
    telemetry_series: Mapping[str, Series] | None,
    temperature: bool,
    clock_offset: ClockOffset | None = None,
) -> tuple[Profiled, ...]:
    """The parameters fitted by profiling: each delayed channel's delay (s), with a reference
    field series the offset between the DUT's and the reference's dates, and, with a
    temperature, the scale per kelvin."""
    profiled: tuple[Profiled, ...] = ()
    if delays:
        from rig.calibration.profiled import clock_offset_parameter, delay_parameter

        if times_s is None:
            raise CalibrationError("--delay needs the sample times: give --time COL (seconds)")
        series = telemetry_series or {}
        profiled = tuple(delay_parameter(data, times_s, c, max_delay_s, series.get(c))
                         for c in delays)  # fmt: skip
        if clock_offset is not None:
            field_at, bound_s = clock_offset
            profiled += (clock_offset_parameter(data, times_s, field_at, bound_s),)
    if temperature:
        from rig.calibration.temperature import scale_parameter

        profiled += (scale_parameter(data),)
    return profiled


def calibrate(
    s: Samples,
    method: Method | None = None,
    *,
    noise_nt: float | None = None,
    robust: RobustLoss | None = None,
    filter_options: FilterOptions | None = None,
    times_s: Array | None = None,
    delays: tuple[str, ...] = (),
    max_delay_s: float = 2.0,
    temperature: Array | None = None,
    temperature_ref: float | None = None,
    telemetry_series: Mapping[str, Series] | None = None,
    clock_offset: ClockOffset | None = None,
) -> CalibrationResult:
    """Fit the measurement model to ``s`` and summarize.

    Args:
        s: the samples (field vector for a vector fit, magnitude for a scalar fit).
        method: estimator; ``None`` picks :func:`default_method`. Scalar methods on data with a field
            vector use only its magnitude (the DUT mounting is then not estimated).
        noise_nt: raw noise 1-sigma per axis (nT) for the chi-square test and the Cramer-Rao bound;
            ``None`` uses the residual estimate.
        robust: ``"huber"`` or ``"bisquare"`` IRLS (``ml`` and ``vector`` only).
        filter_options: variant, backend and start of the sequential filters (``centered-seq``,
            ``ekf``, ``ukf``); they need the raw noise, estimated from the data when not given.
        times_s: sample times (s), for the filters' process noise or forgetting, and the delays.
        delays: telemetry channels whose delay ``tau_j`` to estimate (s, within ``+-max_delay_s``;
            batch methods, needs ``times_s``); see :mod:`rig.calibration.profiled`.
        telemetry_series: per delayed channel, its value at any time (s) when known better than
            by interpolating the column (a run's command log).
        clock_offset: with delays, the reference field at any time (s -> (N, 3) uT) and the bound
            (s) of the DUT-reference date offset fitted with them (``clock_offset_parameter``).
        temperature: DUT temperature per sample (K or degrees C) for the offset and scale
            coefficients per kelvin about ``temperature_ref`` (default: the mean); see
            :mod:`rig.calibration.temperature`.
    """
    est = _checked_estimator(s, method, noise_nt, robust)
    vector = est.model == "vector"
    s, reference = _with_temperature(s, temperature, temperature_ref)
    check_samples(s, (12 if vector else 9) + 3 * s.n_channels)
    data = s if vector else s.as_scalar()
    notes: tuple[str, ...] = ()
    noise_ut = noise_nt / 1000.0 if noise_nt is not None else None
    start, coverage = _check_coverage(data, est.name, robust) if not vector else (None, ())
    if est.kind == "sequential" and noise_ut is None:
        noise_ut = _batch_noise_ut(data, None if start is None else start.p)
        notes += (f"raw noise {1000 * noise_ut:.3g} nT estimated from a batch maximum-likelihood"
                  " fit (give --noise-nt to set it)",)  # fmt: skip
    if est.kind == "batch" and not vector and s.field_ut is not None:
        notes = ("field vector given but a scalar method chosen: only |h| was used",)
    notes += coverage
    profiled = _profiled_parameters(data, times_s, delays, max_delay_s, telemetry_series,
                                    temperature is not None, clock_offset)  # fmt: skip
    if profiled:
        result = _profiled(data, est, noise_ut, robust, times_s, profiled, notes, telemetry_series)
        return replace(result, temperature_ref=reference)
    request = FitRequest(est.name, noise_ut, robust, filter_options, times_s, start)
    return summarize(_estimate(est, data, request, bool(coverage)), data, noise_nt, notes)


def _estimate(est: Estimator, data: Samples, request: FitRequest, one_sided: bool) -> Estimate:
    """``est`` run on ``data``; on ``one_sided`` directions without the noise bias where the
    method can remove it, else with the bias carried in its sigmas (without a robust loss,
    whose weights the bias does not model)."""
    estimate = est.run(data, request)
    if not one_sided or request.robust is not None:
        return estimate
    from rig.calibration.identifiability import (
        NOISE_BIAS_REMOVED,
        with_noise_bias_in_sigmas,
        without_noise_bias,
    )

    if est.name in NOISE_BIAS_REMOVED:
        return without_noise_bias(estimate, data)
    return with_noise_bias_in_sigmas(estimate, data)


def _profiled(
    data: Samples,
    est: Estimator,
    noise_ut: float | None,
    robust: RobustLoss | None,
    times_s: Array | None,
    params: tuple[Profiled, ...],
    notes: tuple[str, ...],
    series: Mapping[str, Series] | None,
) -> CalibrationResult:
    """Find ``params`` (delays, temperature scale) by refitting with ``est``, then summarize;
    ``series``: the delayed channels given as series (a run's), not as their column."""
    if est.kind != "batch":
        raise CalibrationError(
            f"--delay and --temperature need a batch method (the refit at every trial value), not"
            f" {est.name}: use --method ml or vector"
        )

    from rig.calibration.profiled import profile_fit

    def refit(trial: Samples) -> Estimate:
        return est.run(trial, FitRequest(est.name, noise_ut, robust, None, times_s, None))

    fit = profile_fit(data, params, refit, noise_ut=noise_ut)
    noise_nt = None if noise_ut is None else 1000.0 * noise_ut
    notes += (
        "delays and temperature scale found by refitting at trial values; the other parameters'"
        " sigmas include their uncertainty",
    )
    result = replace(summarize(fit.estimate, fit.samples, noise_nt, notes), profiled=fit)
    result = _delays_on_the_sample_grid(result, data, times_s, series or {})
    assert result.profiled is not None
    # the others as uncertain as the delays they were refitted at move them (issue 34 audit:
    # a current coefficient at rms z 1.26 when a delay was known only to a sample interval)
    return replace(result, covariance=result.profiled.marginal_covariance(result.covariance))


ON_GRID = 0.01
"""A delay within this fraction of the sample interval of a whole number of intervals is on the
sample grid (:func:`_delays_on_the_sample_grid`)."""


def _delays_on_the_sample_grid(
    result: CalibrationResult, data: Samples, times_s: Array | None, series: Mapping[str, Series]
) -> CalibrationResult:
    """``result`` with the delays of step-like columns that the fit put on the sample grid
    moved to the middle of the sample interval before, with that interval in their sigma.

    A column held between rows and jumping between two (a current switched in step with the
    samples, recorded at the sample times) is a ramp between those rows to the model. When the
    current really stepped at a sample time, every delay in ``(tau - dt, tau]`` gives the DUT the
    same data, and the model's ramps make a sharp optimum at ``tau`` that the data do not hold:
    the fit lands on a whole number of intervals, its profile sigma a fraction of a millisecond,
    the truth anywhere in the interval before (issue 34 audit: rms z 40). Steps at random times
    leave the estimate anywhere in the interval (their ramps' misfit enters the sigma, see
    ``rig.calibration.profiled``); its sigma is at least ``dt / sqrt(12 n)`` for ``n`` steps
    (near the grid the misfit at the estimate vanishes: 4 of 200 audit draws were 4-7 sigma off
    without that floor). A run's channels come as command series, not here."""
    fit = result.profiled
    if fit is None or times_s is None:
        return result
    from rig.calibration.profiled import with_resolution

    dt = float(np.median(np.diff(times_s)))
    values, widths, notes = fit.values.copy(), {}, []
    floors = np.zeros(values.size)
    for i, prm in enumerate(fit.params):
        if prm.group != "delay_s" or prm.key in series:
            continue
        jumps = np.flatnonzero(np.diff(data.telemetry[:, data.channels.index(prm.key)]))
        if jumps.size < 2 or not np.all(np.diff(jumps) > 1):
            continue
        if abs(values[i] / dt - round(values[i] / dt)) > ON_GRID:
            # each step's time is known only within its interval: n steps at independent
            # times pin the delay to dt / sqrt(12 n) at best, whatever the misfit at the estimate
            floors[i] = dt / np.sqrt(12.0 * jumps.size)
            continue
        values[i] -= dt / 2.0
        widths[prm.key] = dt
        notes.append(f"delay[{prm.key}]: its steps fall on the sample grid, so it is known only to"
                     f" within the {1000 * dt:.3g} ms interval before {1000 * fit.values[i]:.4g}"
                     " ms: its middle is given, its sigma includes that interval")  # fmt: skip
    fit = with_resolution(replace(fit, values=values, sigma=np.maximum(fit.sigma, floors)),
                          "delay_s", widths)  # fmt: skip
    return replace(result, profiled=fit, warnings=(*result.warnings, *notes))


def _check_coverage(
    s: Samples, method: str, robust: RobustLoss | None = None
) -> tuple[Estimate | None, tuple[str, ...]]:
    """Identifiability of a scalar fit on ``s``, from the Fisher information at the linear
    start's maximum-likelihood fit (docs/adr/0026): CalibrationError naming a combination the data
    cannot determine; else the start (the linear one, or the nominal sensor where the fit runs off
    from that) and warnings when field directions are missing."""
    from rig.calibration.batch.nonlinear import scalar_start
    from rig.calibration.identifiability import check_identifiable, converging_start

    linear = method in ("centered", "ellipsoid", "twostep")
    start: Estimate | None = None
    try:
        # Only the linear estimators report their start as their answer: the others need a start.
        start = scalar_start(s, quick=not linear)
    except (CalibrationError, np.linalg.LinAlgError):
        if linear:
            return None, ()
    found = None if linear else converging_start(s, None if start is None else start.p)
    if found is not None and (start is None or found[0] is not start.p):
        start = Estimate("nominal-start", found[0], np.zeros((found[0].size,) * 2))
    if start is None:
        return None, ()
    # the bias is removed or carried in the sigmas whenever there is no robust loss
    info = None if found is None else found[1]  # the fit from this start, already made
    return start, check_identifiable(s, start.p, method, robust is None, info)


def _batch_noise_ut(s: Samples, start: Array | None = None) -> float:
    """Raw noise 1-sigma (uT) from the residuals of a scalar ML fit (any sample order);
    ``start``: its linear start, when already computed."""
    est = ml_fit(s, start=start)
    r = scalar_residuals_only(est.p, s) / scalar_noise_gain(est.p, s)
    return float(np.sqrt(np.sum(r**2) / max(s.n - est.p.size, 1)))
