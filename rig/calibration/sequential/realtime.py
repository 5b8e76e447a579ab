"""Real-time calibration: build a sequential filter, run it over samples, report its estimate.

Methods (``rig calibrate --method``): the modules registered in :data:`rig.calibration.sequential.KINDS`,
each building its own filter. Variants: ``energy``
(default; :mod:`rig.calibration.sequential.energy_filter`, converges from a zero start), ``paper``
(the paper's filters as published: EKF eqs. 25-27, 9-state UKF) and ``paper-augmented`` (12-state
UKF, eq. 47). Backends: ``numpy`` (in-house) and ``filterpy`` (the paper variants, through
filterpy's ``ExtendedKalmanFilter`` and ``UnscentedKalmanFilter``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rig.calibration.estimate import Estimate, FilterHistory, delta_method
from rig.calibration.params import Array
from rig.calibration.residuals import Samples, p_from_theta
from rig.calibration.sequential import sequential_kind
from rig.calibration.sequential.filters import initial_covariance
from rig.calibration.sequential.guard import DivergenceWatch, GuardReport, check_final
from rig.calibration.sequential.kind import FilterOptions, SequentialFilter

__all__ = ["FilterOptions", "SequentialFilter", "filter_estimate", "make_filter", "run_filter"]
from rig.calibration.sequential.zmodel import ZModel, z_sample
from rig.errors import CalibrationError


def make_filter(opts: FilterOptions, n_channels: int, noise_ut: float) -> SequentialFilter:
    """A filter for ``n_channels`` telemetry channels and raw noise ``noise_ut`` (uT, 1-sigma):
    the one the options' method builds (its module in this package)."""
    model = ZModel(n_channels, noise_ut)
    p0 = initial_covariance(n_channels, opts.bias_sigma_ut, opts.e_sigma, opts.k_sigma_ut_per_unit)
    return sequential_kind(opts.method).build(opts, model, p0)


def noise_from_second_differences(measured_ut: Array) -> float:
    """Raw noise 1-sigma (uT) from the median absolute second difference of the readings.

    Second differences cancel a smoothly changing field and the median ignores the few samples at
    each step of a cage sequence; white noise of sigma gives a second difference of sigma sqrt(6).
    """
    m = np.asarray(measured_ut, float)
    if m.shape[0] < 5:
        raise CalibrationError("too few samples to estimate the noise: give --noise-nt")
    d2 = np.diff(m, n=2, axis=0).reshape(-1)
    mad = float(np.median(np.abs(d2)))
    sigma = mad / 0.6744897501960817 / np.sqrt(6.0)
    if not sigma > 0:
        raise CalibrationError(
            "the readings do not change at all (no noise to estimate): give --noise-nt"
        )
    return float(sigma)


def run_filter(
    s: Samples,
    opts: FilterOptions,
    noise_ut: float,
    *,
    times_s: Array | None = None,
    history_rows: int = 400,
    progress: Any = None,
) -> tuple[Estimate, FilterHistory]:
    """Run the filter over every sample in order; return the final estimate and its history.

    ``history_rows`` bounds the recorded rows (the last sample is always recorded); ``progress``
    is called with the sample index every 1000 samples. A filter whose innovations say it has
    diverged is re-initialized from the batch estimate of the samples so far, and a final answer
    far worse than the batch estimate of all samples is refused (:mod:`.guard`).
    """
    kind = sequential_kind(opts.method)
    f = make_filter(opts, s.n_channels, noise_ut)
    guarded = kind.guarded
    watch = DivergenceWatch()
    every = max(1, s.n // max(history_rows, 1))
    idx: list[int] = []
    xs: list[Array] = []
    covs: list[Array] = []
    nis = np.full(s.n, np.nan)
    t_prev = None
    for k in range(s.n):
        u = s.telemetry[k] if s.n_channels else np.zeros(0)
        dt = 0.0
        if times_s is not None:
            dt = 0.0 if t_prev is None else float(times_s[k] - t_prev)
            t_prev = float(times_s[k])
        try:
            info = f.update(z_sample(s.measured_ut[k], float(s.field_magnitude_ut[k]), u), dt)
        except np.linalg.LinAlgError as exc:
            raise CalibrationError(
                f"the {opts.method} filter lost positive definiteness at sample {k + 1}: start with"
                " --filter-variant energy, or give a realistic --noise-nt"
            ) from exc
        if info is not None:
            nis[k] = info.nis
        if guarded and watch.diverged(k, None if info is None else info.nis):
            watch.reinitialize(f, s.head(k + 1), k)
        if f.ready and ((k + 1) % every == 0 or k == s.n - 1):
            idx.append(k)
            xs.append(f.x[: 9 + 3 * s.n_channels].copy())
            covs.append(f.P[: 9 + 3 * s.n_channels, : 9 + 3 * s.n_channels].copy())
        if progress is not None and k % 1000 == 0:
            progress(k)
    if not f.ready:
        raise CalibrationError(
            f"{opts.method}: the data never made the calibration observable: {kind.needs}"
        )
    if guarded:
        check_final(np.asarray(f.x[: 9 + 3 * s.n_channels], float), s, noise_ut, opts.method,
                    watch.report)  # fmt: skip
    est = filter_estimate(f, s.n_channels, opts, noise_ut, nis, (idx, xs, covs), watch.report)
    assert est.history is not None
    return est, est.history


def filter_estimate(
    f: SequentialFilter,
    n_channels: int,
    opts: FilterOptions,
    noise_ut: float,
    nis: Array,
    recorded: tuple[list[int], list[Array], list[Array]],
    guard: GuardReport | None = None,
) -> Estimate:
    """The physical estimate of a filter that has seen every sample, with its history.

    ``nis`` holds one entry per sample (NaN where there was no update); ``recorded`` is the
    (sample index, theta, covariance) rows kept along the way.
    """
    n_theta = 9 + 3 * n_channels
    x, big_p, final_note = f.final()
    theta = np.asarray(x[:n_theta], float)
    cov_theta = np.asarray(big_p[:n_theta, :n_theta], float)
    p, cov = delta_method(p_from_theta, theta, cov_theta, opts.method)
    mean_nis = float(np.nanmean(nis)) if np.any(np.isfinite(nis)) else float("nan")
    note: tuple[str, ...] = (
        f"{opts.method} ({opts.variant}, {opts.backend}) over {nis.size} samples at"
        f" {1000 * noise_ut:.3g} nT raw noise; mean NIS {mean_nis:.2f} (1 when consistent)",
    )
    if final_note is not None:
        note += (final_note,)
    if guard is not None and guard.recoveries:
        note += (
            f"diverged and was re-initialized from the batch estimate at sample(s)"
            f" {', '.join(str(k + 1) for k in guard.recoveries)}",
        )
    if guard is not None and np.isfinite(guard.final_excess):
        note += (
            f"fits {guard.final_excess:.1f} chi-square units worse than the batch fit of the same"
            f" samples (converged: under {guard.limit:.0f})",
        )
    idx, xs, covs = recorded
    history = FilterHistory(
        np.asarray(idx, int),
        np.asarray(xs).reshape(-1, n_theta),
        np.asarray(covs).reshape(-1, n_theta, n_theta),
        nis,
        theta,
        cov_theta,
    )
    return Estimate(opts.method, p, cov, notes=note, history=history)


def history_table(history: FilterHistory, names: tuple[str, ...]) -> tuple[list[str], Array]:
    """Physical parameters and 1-sigma per recorded row: header and (R, 1 + 2 P) array."""
    rows = []
    for theta, cov_theta in zip(history.theta, history.covariance, strict=True):
        try:
            p, cov = delta_method(p_from_theta, theta, cov_theta, "filter")
            rows.append(np.concatenate([p, np.sqrt(np.clip(np.diag(cov), 0, None))]))
        except CalibrationError:
            rows.append(np.full(2 * len(names), np.nan))
    header = ["sample"] + list(names) + [f"sigma_{n}" for n in names]
    body = (
        np.column_stack([history.index + 1, np.asarray(rows)])
        if rows
        else np.zeros((0, len(header)))
    )
    return header, body
