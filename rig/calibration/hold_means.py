"""Sigmas from how the holds' means scatter about the fit, where the field was held (issue 55).

A calibration on held fields learns its parameters from each hold's mean reading: what the
samples within a hold share (a lab field that wanders) stays in the mean, what alternates between
them (mains ripple aliased by the sampling: 50 Hz read at 20 Hz alternates sample by sample)
averages out of it. The per-sample scatter misstates the mean's error both ways, by up to 2x on
the simulated cage's vertical axis (20-36 nT per sample where the means scatter as 20 nT would).
So where the samples are numbered by hold (:attr:`Samples.holds`), the noise per series (a
vector fit's axis, or the scalar fit's one) is taken from the means instead: with ``rho_h =
sum_k w_k r_k / sqrt(n_h)`` (``n_h = sum_k w_k`` the hold's weight) the variance a sample would
need for the means to scatter so is ``v_s = sum_h rho_hs^2 / (H - tr_s)``, ``tr_s`` the
leverage the fit takes from series ``s``'s hold means (the trace of the hat matrix of the
hold-mean regression, ``sum_s tr_s`` = the fitted parameters). The sigmas are then
``H^-1 (sum_s v_s H_s) H^-1`` (``H_s`` the normal matrix from series ``s``) against the same with
the per-sample variances: per parameter a factor above or below 1. What moves slower than a hold
(the hold means correlated in time) is :func:`rig.calibration.correlated.rows_noise_check`'s on
the hold-mean series, which only inflates.

Needs enough holds: at least :data:`MIN_HOLD_DOF` hold means per series beyond the leverage the
fit takes from them; else the per-sample model stands (ADR 0025).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from rig.calibration.correlated import RowsFunction, rows_noise_check
from rig.calibration.params import Array
from rig.calibration.residuals import Holds, row_blocks
from rig.calibration.solver import covariance_from_normal
from rig.calibration.stats import f_sf

SLOW_P_VALUE = 0.01
"""The hold means count as scattering beyond what the samples within the holds say when the ratio
of their variance to that one has an F test's p-value below this (both estimated, each with its
degrees of freedom: a chi-square against the within-hold variance as if known had flagged 1.8 %
of white-noise series on the designed acceptance's 19 holds, not 1 %)."""
MIN_HOLD_DOF = 8.0
"""The fewest degrees of freedom (hold means less their leverage) per series for the hold-mean
noise: with 8 a variance is known to +-50 % (2 sigma), as the per-sample model's worst case."""


@dataclass(frozen=True)
class HoldNoise:
    """The sigmas' factors from the hold means and what they rest on.

    ``variance_factors`` (P,): per parameter the sigma under the noise the means see over the
    per-sample white sigma; ``between_inflation`` (P,): the hold-mean series' own inflation for
    correlation between holds, over ``between_bandwidth`` holds (0: white); both 1 for a held
    parameter; ``holds``: hold means used; ``variance_ratio`` (S,): per series that noise's
    variance over the per-sample one; ``slow`` (S,): the hold means scattered beyond what the
    samples within the holds say (their own variance then); ``crlb``: the Cramer-Rao bound
    (P, P; uT and rad squared) for that noise, independent between holds.
    """

    variance_factors: Array
    between_inflation: Array
    between_bandwidth: int
    holds: int
    variance_ratio: Array
    slow: npt.NDArray[np.bool_]
    crlb: Array

    def factors(self, sample_inflation: Array) -> Array:
        """The factors on the white sigmas: the noise's, times the larger of the correlation
        between holds and ``sample_inflation`` (the per-sample check's, for correlation the hold
        test is too coarse to see), the latter only when no series is slow (its hold means then
        hold every correlation within the holds already)."""
        between = self.between_inflation
        if not np.any(self.slow):
            between = np.maximum(between, sample_inflation)
        return np.asarray(self.variance_factors * between)


@dataclass(frozen=True)
class _Means:
    """Group means (holds or pairs) as rows of a regression: ``rho`` (G, S) the weighted residual
    sums over the root of their weight, ``rows`` (G, S, P) the Jacobian likewise, and per series
    the variance per sample they imply and its degrees of freedom."""

    rho: Array
    rows: Array
    variance: Array
    dof: Array


def hold_noise(
    series: Array,
    jac_rows: RowsFunction,
    weights: Array,
    holds: Holds,
    white_variance: float | Array,
    fitted: npt.NDArray[np.bool_],
) -> HoldNoise | None:
    """The noise hold means see (see the module) for residual ``series`` (N, S; uT, not
    weighted), their Jacobian rows ``jac_rows`` (slice -> (B, S, P)), per-sample robust
    ``weights`` (N,), hold numbers ``holds`` (N,), the per-sample white variance per series
    ``white_variance`` (S,; uT^2) and the ``fitted`` parameters (P,); None when the holds are
    too few."""
    index = np.unique(holds, return_inverse=True)[1].reshape(-1)
    pairs = _pair_index(index)
    (hold_sums, pair_sums), normal = _group_sums(series, jac_rows, weights, (index, pairs), fitted)
    h_inv = covariance_from_normal(normal.sum(axis=0), 1.0)
    hold = _means(*hold_sums, h_inv)
    pair = _means(*pair_sums, h_inv)
    if hold is None or float(np.min(hold.dof)) < MIN_HOLD_DOF:
        return None
    per_sample = np.broadcast_to(np.asarray(white_variance, float), hold.variance.shape)
    # the per-sample variance's degrees of freedom: each series charged its share of the fit
    sample_dof = np.full(
        per_sample.shape, max(series.shape[0] - fitted.sum() / series.shape[1], 1.0)
    )
    within, within_dof = per_sample, sample_dof
    if pair is not None:
        by_pairs = pair.variance < per_sample
        within = np.where(by_pairs, pair.variance, per_sample)
        within_dof = np.where(by_pairs, pair.dof, sample_dof)
    slow = np.array([f_sf(float(v / max(w, 1e-300)), float(d), float(e)) < SLOW_P_VALUE
                     for v, w, d, e in zip(hold.variance, within, hold.dof, within_dof, strict=True)])  # fmt: skip
    use = np.where(slow, hold.variance, within)
    between, _, _ = rows_noise_check(hold.rho.reshape(-1), hold.rows.reshape(-1, h_inv.shape[0]),
                                     hold.rho.shape[0], use)  # fmt: skip
    white = _sandwich_diagonal(h_inv, normal, per_sample)
    factors, inflation = np.ones(fitted.size), np.ones(fitted.size)
    factors[fitted] = np.sqrt(_sandwich_diagonal(h_inv, normal, use) / np.maximum(white, 1e-300))
    inflation[fitted] = between.inflation
    crlb = np.zeros((fitted.size, fitted.size))
    info = np.einsum("s,spq->pq", 1.0 / np.maximum(use, 1e-300), normal)
    crlb[np.ix_(fitted, fitted)] = covariance_from_normal(info, 1.0)
    ratio = use / np.maximum(per_sample, 1e-300)
    return HoldNoise(factors, inflation, between.bandwidth, int(hold.rho.shape[0]), ratio, slow,
                     crlb)  # fmt: skip


def _pair_index(index: npt.NDArray[np.intp]) -> npt.NDArray[np.intp]:
    """Per sample its pair (consecutive samples of one hold, the first two, the next two, ...;
    -1 for a hold's odd last sample): a pair's mean cancels what alternates sample by sample."""
    n = index.size
    order = np.argsort(index, kind="stable")
    ranked = index[order]
    starts = np.r_[0, np.flatnonzero(np.diff(ranked)) + 1] if n else np.zeros(0, np.intp)
    lengths = np.diff(np.r_[starts, n])
    position = np.arange(n) - np.repeat(starts, lengths)
    paired = position < np.repeat(lengths - lengths % 2, lengths)
    first = paired & (position % 2 == 0)
    out = np.full(n, -1, dtype=np.intp)
    out[order] = np.where(paired, np.cumsum(first) - 1, -1)
    return out


def _group_sums(
    series: Array,
    jac_rows: RowsFunction,
    weights: Array,
    groupings: tuple[npt.NDArray[np.intp], ...],
    fitted: npt.NDArray[np.bool_],
) -> tuple[list[tuple[Array, Array, Array]], Array]:
    """Per grouping (group number per sample, -1 for none) the groups' weighted sums of residuals
    (G, S), of Jacobian rows (G, S, P) and their weights (G,), block by block; last the normal
    matrix per series (S, P, P)."""
    n, n_series = series.shape
    n_params = int(np.count_nonzero(fitted))
    sizes = [int(g.max()) + 1 if g.size and g.max() >= 0 else 0 for g in groupings]
    sums = [(np.zeros((m, n_series)), np.zeros((m, n_series, n_params)), np.zeros(m))
            for m in sizes]  # fmt: skip
    normal = np.zeros((n_series, n_params, n_params))
    for rows in row_blocks(n):
        w = weights[rows]
        jac = jac_rows(rows)[:, :, fitted]
        normal += np.einsum("bsp,bsq,b->spq", jac, jac, w)
        for g, (residual, jacobian, weight) in zip(groupings, sums, strict=True):
            at, keep = g[rows], g[rows] >= 0
            np.add.at(residual, at[keep], series[rows][keep] * w[keep, None])
            np.add.at(jacobian, at[keep], jac[keep] * w[keep, None, None])
            np.add.at(weight, at[keep], w[keep])
    return sums, normal


def _means(residual: Array, jacobian: Array, weight: Array, h_inv: Array) -> _Means | None:
    """The groups as a regression's rows and the variance per sample their scatter about the fit
    implies: ``sum rho^2 / (G - leverage)`` per series, its degrees of freedom at least 1 (None
    without groups)."""
    used = weight > 0
    if not np.any(used):
        return None
    root_n = np.sqrt(weight[used])
    rho = residual[used] / root_n[:, None]
    rows = jacobian[used] / root_n[:, None, None]
    dof = np.maximum(rho.shape[0] - np.einsum("gsp,pq,gsq->s", rows, h_inv, rows), 1.0)
    return _Means(rho, rows, np.sum(rho**2, axis=0) / dof, dof)


def _sandwich_diagonal(h_inv: Array, normal_by_series: Array, variance: Array) -> Array:
    """``diag(H^-1 (sum_s v_s H_s) H^-1)``."""
    middle = np.einsum("s,spq->pq", variance, normal_by_series)
    return np.asarray(np.diag(h_inv @ middle @ h_inv))
