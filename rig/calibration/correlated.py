"""Residual whiteness, and sigmas and a Cramer-Rao bound that hold for correlated residuals.

Every fit's covariance assumes independent residuals. Here (ADR 0025):

* **Whiteness**: the Ljung-Box portmanteau statistic (Ljung and Box 1978) of the residual series in
  sample order (one series for a scalar fit, one per axis for a vector fit), at
  :data:`LJUNG_BOX_LAGS` lags, and the excess kurtosis of the standardized residuals.
* **Sigmas when correlated**: per parameter the larger of two sandwiches ``H^-1 M H^-1`` (``H``
  the noise-weighted normal matrix). Model-free: ``M = N S``, ``S`` the long-run covariance of
  the per-sample scores ``g_k = J_k^T r_k`` from overlapping block sums of ``b`` samples, the
  Bartlett-kernel (Newey-West 1987) estimator with bandwidth ``b`` up to edge terms (Kuensch 1989:
  the moving-block bootstrap's variance is this estimator), ``b`` from Andrews' (1991) AR(1)
  plug-in rule; it runs low when the correlation time is a sizeable part of ``b``. Model-based:
  ``M = J^T Sigma J`` with ``Sigma`` the covariance of the residuals' AR(p) model (the same model
  as the bound below; Berk 1974's autoregressive spectral estimate at frequency zero, taken
  through the regressors), computed by filtering the Jacobian backward through the model's
  inverse; it runs low when the correlation is not autoregressive (a missing term). Each
  parameter's sigma is multiplied by its factor ``sqrt(sandwich / white)``, never below 1;
  correlations stay the estimator's own.
* **Cramer-Rao bound for the same noise**: an AR(p) model of the residuals (Yule-Walker by
  Levinson-Durbin, order by AIC up to :data:`MAX_AR_ORDER`) whitens the Jacobian column by column;
  the bound is ``sigma_e^2 (J_w^T J_w)^-1`` with ``sigma_e^2`` the innovation variance.

Pure numpy; the scores and Jacobian rows come in blocks of rows (bounded memory, ADR 0017).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rig.calibration.params import Array
from rig.calibration.residuals import (
    Samples,
    row_blocks,
    scalar_jacobian_rows,
    scalar_residuals_and_gain,
)
from rig.calibration.stats import chi2_sf

LJUNG_BOX_LAGS = 20
"""Lags of the Ljung-Box statistic (fewer on short series: a fifth of the samples)."""
WHITE_P_VALUE = 0.01
"""Residuals count as correlated when the Ljung-Box p-value (Bonferroni over the series) is below
this."""
HEAVY_TAIL_EXCESS_KURTOSIS = 1.0
"""Excess kurtosis above this (and five standard errors, ``5 sqrt(24 / N)``) counts as heavy tails
(a Gaussian has 0, Student t with 5 dof 6)."""
MAX_AR_ORDER = 10
"""Highest order of the autoregressive noise model behind the Cramer-Rao bound."""

RowsFunction = Callable[[slice], Array]
"""Rows ``rows`` of a per-sample array (scores (B, P), or Jacobian rows (B, S, P) per series)."""


@dataclass(frozen=True)
class NoiseCheck:
    """What the residuals say about the noise model, and what was done about it.

    ``lag1``: lag-1 autocorrelation (the largest over the series); ``ljung_box``/``p_value``: the
    portmanteau statistic at ``lags`` lags and its (Bonferroni) p-value; ``inflation``: per
    parameter, reported sigma / white-noise sigma (all 1 when white and no hold means);
    ``bandwidth``: block length of the long-run covariance (samples, 0 when white); ``ar_order``:
    order of the noise model of the Cramer-Rao bound (0: white); ``holds``: hold means the sigmas
    come from (:mod:`rig.calibration.hold_means`; 0: from the samples), ``hold_variance_ratio`` per
    series their variance over the samples', ``between_holds``: whether the hold means correlate in
    time (their bandwidth in holds, else 0).
    """

    lag1: float
    ljung_box: float
    lags: int
    p_value: float
    excess_kurtosis: float
    correlated: bool
    heavy_tailed: bool
    inflation: Array
    bandwidth: int = 0
    ar_order: int = 0
    holds: int = 0
    hold_variance_ratio: tuple[float, ...] = ()
    between_holds: int = 0

    @property
    def method(self) -> str:
        """How the reported sigmas were obtained."""
        if self.holds:
            between = (f", a Newey-West sandwich over {self.between_holds} holds for their"
                       " correlation in time" if self.between_holds else "")  # fmt: skip
            return (
                f"the noise {self.holds} hold means see (per axis the pair means of"
                " consecutive samples, or the hold means where they scatter more)" + between
            )
        if not self.correlated:
            return "white-noise least squares"
        return (
            f"the larger of a Newey-West (HAC) sandwich, Bartlett bandwidth {self.bandwidth}"
            f" samples, and the sandwich under an AR({self.ar_order}) noise model"
        )

    def notes(self, robust: bool) -> list[str]:
        """The one-line statements for the output (empty when white and light-tailed)."""
        out = []
        lo, hi = float(np.min(self.inflation)), float(np.max(self.inflation))
        if self.correlated:
            factor = (f"factor {lo:.2f}-{hi:.2f} on the white-noise sigmas" if self.holds
                      else f"inflation factor {lo:.2f}-{hi:.2f}")  # fmt: skip
            bound = "that noise" if self.holds else f"an AR({self.ar_order}) noise"
            out.append(
                f"residuals correlated (Ljung-Box p {_p_text(self.p_value)} at {self.lags} lags),"
                f" lag-1 r = {self.lag1:.2f}: sigmas from {self.method}, {factor}; Cramer-Rao"
                f" bound for {bound} (correlated residuals can also mean a missing term: a channel,"
                " a delay)"
            )
        elif self.holds and (lo < 0.9 or hi > 1.1):
            out.append(f"sigmas from {self.method}: factor {lo:.2f}-{hi:.2f} on the white-noise"
                       " sigmas (a hold's samples scatter unlike its mean's error: mains ripple the"
                       " sampling aliases averages out of it, a wander over a hold does not)")  # fmt: skip
        if self.heavy_tailed:
            out.append(
                f"residuals heavy-tailed (excess kurtosis {self.excess_kurtosis:.1f}, 0 for"
                " Gaussian noise): outliers weigh in the fit"
                + ("" if robust else "; try --robust huber")
            )
        return out

    def to_dict(self) -> dict[str, object]:
        """The ``residual_whiteness`` block of the result file."""
        return {
            "correlated": self.correlated,
            "lag1_autocorrelation": self.lag1,
            "ljung_box": self.ljung_box,
            "lags": self.lags,
            "p_value": self.p_value,
            "excess_kurtosis": self.excess_kurtosis,
            "heavy_tailed": self.heavy_tailed,
            "sigma_method": self.method,
            "bandwidth_samples": self.bandwidth,
            "inflation": {
                "min": float(np.min(self.inflation)),
                "max": float(np.max(self.inflation)),
            },
            "crlb_noise_model": f"AR({self.ar_order})" if self.ar_order else "white",
            "hold_means": self.holds,
            "hold_variance_ratio": list(self.hold_variance_ratio),
        }


def _p_text(p: float) -> str:
    """``= 0.0012`` or ``< 1e-16`` (below double precision's resolution of 1 - p)."""
    return f"= {p:.2g}" if p >= 1e-16 else "< 1e-16"


def autocovariance(x: Array, lags: int) -> Array:
    """Biased autocovariances of the columns of ``x`` (N, S) about their means at lags 0..lags,
    shape (lags + 1, S), by direct products (no N-sized temporaries beyond the centred copy)."""
    xc = x - x.mean(axis=0)
    n = x.shape[0]
    return np.array([np.einsum("ij,ij->j", xc[: n - k], xc[k:]) / n for k in range(lags + 1)])


def ljung_box(x: Array, lags: int) -> tuple[Array, Array, Array]:
    """Ljung-Box ``Q = N (N + 2) sum_k r_k^2 / (N - k)`` of each column of ``x`` (N, S); returns
    ``Q`` (S,), its chi-square p-values (S,) and the autocorrelations (lags + 1, S)."""
    n = x.shape[0]
    acov = autocovariance(x, lags)
    r = acov / np.maximum(acov[0], 1e-300)
    k = np.arange(1, lags + 1)[:, None]
    q = n * (n + 2.0) * np.sum(r[1:] ** 2 / (n - k), axis=0)
    return q, np.array([chi2_sf(float(v), lags) for v in q]), r


def andrews_bandwidth(rho: float, n: int) -> int:
    """Bartlett-kernel bandwidth (samples) of Andrews (1991) eq. 6.2 for AR(1) scores with lag-1
    autocorrelation ``rho``: ``1.1447 (alpha N)^(1/3)``, ``alpha = 4 rho^2 / ((1-rho)^2
    (1+rho)^2)``; at least 2, at most ``N / 8``."""
    rho = min(max(rho, 0.0), 0.995)
    alpha = 4.0 * rho**2 / ((1.0 - rho) ** 2 * (1.0 + rho) ** 2)
    return int(min(max(math.ceil(1.1447 * (alpha * n) ** (1.0 / 3.0)), 2), max(n // 8, 2)))


def long_run_covariance(scores: RowsFunction, n: int, bandwidth: int) -> Array:
    """Long-run covariance per sample ``lim Var(sum g_k) / N`` of the score rows (P,) from the
    centred sums of every window of ``bandwidth`` consecutive rows, divided by the window length;
    blockwise with the cumulative sum carried over."""
    b = bandwidth
    tail: Array | None = None  # cumulative sums C_j for the last b + 1 indices j (C_0 = 0)
    outer: Array | None = None
    total: Array | None = None
    count = 0
    first = 0  # the index j of tail[0]
    for rows in row_blocks(n):
        g = scores(rows)
        if tail is None:
            tail = np.zeros((1, g.shape[1]))
            outer = np.zeros((g.shape[1], g.shape[1]))
            total = np.zeros(g.shape[1])
        cum = np.vstack([tail, tail[-1] + np.cumsum(g, axis=0)])
        ends = np.arange(max(rows.start + 1, b), rows.stop + 1)
        if ends.size:
            w = cum[ends - first] - cum[ends - b - first]
            assert outer is not None and total is not None
            outer += w.T @ w
            total += w.sum(axis=0)
            count += ends.size
        tail = cum[-(b + 1) :]
        first = rows.stop - (tail.shape[0] - 1)
    assert outer is not None and total is not None and count > 0
    mean = total / count
    return (outer / count - np.outer(mean, mean)) / b


def ar_model(acov: Array, max_order: int = MAX_AR_ORDER, n: int = 0) -> tuple[Array, float]:
    """AR coefficients ``phi`` (p,) and the innovation/marginal variance ratio of the series with
    autocovariances ``acov`` (lags 0..), by Levinson-Durbin, the order minimizing AIC
    ``n ln(v_p) + 2 p`` (``n``: the series length)."""
    order = min(max_order, acov.size - 1)
    phi = np.zeros(0)
    v = float(acov[0])
    best = (n * math.log(1.0), np.zeros(0), 1.0)
    for p in range(1, order + 1):
        k = (acov[p] - phi @ acov[1:p][::-1]) / v
        phi = np.concatenate([phi - k * phi[::-1], [k]])
        v *= 1.0 - k * k
        if v <= 0:
            break
        aic = n * math.log(v / acov[0]) + 2 * p
        if aic < best[0]:
            best = (aic, phi.copy(), v / float(acov[0]))
    return best[1], best[2]


def whitened_information(jac_rows: RowsFunction, n: int, phi: Array) -> Array:
    """``J_w^T J_w`` with ``J_w[k] = J[k] - sum_i phi_i J[k-i]`` per series, the Jacobian rows
    (B, S, P) filtered by the AR model (the first rows of each series taken as they are)."""
    p = phi.size
    info: Array | None = None
    carry: Array | None = None
    for rows in row_blocks(n):
        jac = jac_rows(rows)
        ext = jac if carry is None else np.concatenate([carry, jac])
        off = ext.shape[0] - jac.shape[0]
        w = jac.copy()
        for i in range(1, p + 1):
            lo = max(i - off, 0)  # rows of this block with a predecessor i rows back
            w[lo:] -= phi[i - 1] * ext[off + lo - i : ext.shape[0] - i]
        flat = w.reshape(-1, w.shape[-1])
        info = flat.T @ flat if info is None else info + flat.T @ flat
        carry = ext[-p:] if p else None
    assert info is not None
    return info


def ar_long_run_information(jac_rows: RowsFunction, n: int, phi: Array, weights: Array) -> Array:
    """``Y^T Y`` with ``Y = L^-T (W J)``: the Jacobian rows (B, S, P) times per-sample
    ``weights`` (n,), filtered backward in time by the AR model's inverse ``y_k = x_k + sum_i
    phi_i y_(k+i)`` per series; ``sigma_e^2 Y^T Y`` is ``J^T W Sigma W J`` for AR noise of
    innovation variance ``sigma_e^2`` (blocks from the last, the filter state carried)."""
    from scipy.signal import lfilter

    den = np.concatenate([[1.0], -phi])
    out: Array | None = None
    state: Array | None = None
    for rows in reversed(list(row_blocks(n))):
        x = (jac_rows(rows) * weights[rows, None, None])[::-1]
        if state is None:
            state = np.zeros((phi.size, *x.shape[1:]))
        if phi.size:
            y, state = lfilter([1.0], den, x, axis=0, zi=state)
        else:
            y = x
        flat = np.asarray(y).reshape(-1, x.shape[-1])
        out = flat.T @ flat if out is None else out + flat.T @ flat
    assert out is not None
    return out


def check_noise(
    series: Array,
    scores: RowsFunction,
    jac_rows: RowsFunction,
    normal: Callable[[], Array],
    white_variance: float | Array,
    n_params: int,
    weights: Array | None = None,
) -> tuple[NoiseCheck, Array | None, float]:
    """Test the residual ``series`` (N, S; noise-normalized, in sample order) for whiteness; when
    correlated, the sigma factors over the white covariance ``H^-1 (sum_s v_s H_s) H^-1`` (``H``
    = ``normal()``, ``H_s`` its part from series ``s``, ``v_s`` its ``white_variance``, one for
    all or one per series; ``v H^-1`` when they agree): per parameter the larger of the Bartlett
    sandwich of ``scores`` (per-sample ``J_k^T r_k``, weighted as ``H``) and the sandwich under
    the residuals' AR model of the ``jac_rows`` times the square root of the per-sample
    ``weights`` (robust, default 1; as in the ``series``); and the information ``J_w^T J_w`` of
    the AR-whitened ``jac_rows`` with the AR model's innovation/marginal variance ratio (None, 1
    when white)."""
    n, n_series = series.shape
    lags = max(min(LJUNG_BOX_LAGS, n // 5), 1)
    q, p_values, r = ljung_box(series, lags)
    worst = int(np.argmin(p_values))
    p_value = min(1.0, float(p_values[worst]) * n_series)
    lag1 = float(r[1, int(np.argmax(np.abs(r[1])))])
    z = (series - series.mean(axis=0)) / np.maximum(series.std(axis=0), 1e-300)
    excess = float(np.mean(z**4) - 3.0)
    heavy = excess > max(HEAVY_TAIL_EXCESS_KURTOSIS, 5.0 * math.sqrt(24.0 / (n * n_series)))
    ones = np.ones(n_params)
    if p_value >= WHITE_P_VALUE:
        return (
            NoiseCheck(lag1, float(q[worst]), lags, p_value, excess, False, heavy, ones),
            None,
            1.0,
        )
    bandwidth = andrews_bandwidth(float(np.mean(r[1])), n)
    h_inv = np.linalg.pinv(normal())
    hac = np.diag(h_inv @ (n * long_run_covariance(scores, n, bandwidth)) @ h_inv)
    acov = autocovariance(series, MAX_AR_ORDER)
    phi, ratio = ar_model((acov / np.maximum(acov[0], 1e-300)).mean(axis=1), MAX_AR_ORDER, n)
    variance = np.broadcast_to(np.asarray(white_variance, dtype=np.float64), (n_series,))
    root_w = np.sqrt(np.ones(n) if weights is None else weights)

    def scaled(rows: slice) -> Array:  # each series' rows times its noise 1-sigma
        return np.asarray(jac_rows(rows) * np.sqrt(variance)[None, :, None])

    white = np.diag(h_inv @ ar_long_run_information(scaled, n, np.zeros(0), root_w) @ h_inv)
    modelled = ratio * np.diag(h_inv @ ar_long_run_information(scaled, n, phi, root_w) @ h_inv)
    inflation = np.sqrt(np.maximum(np.maximum(hac, modelled) / np.maximum(white, 1e-300), 1.0))
    info = whitened_information(jac_rows, n, phi)
    check = NoiseCheck(lag1, float(q[worst]), lags, p_value, excess, True, heavy, inflation,
                       bandwidth, phi.size)  # fmt: skip
    return check, info, ratio


def rows_noise_check(
    r: Array, jac: Array, n: int, white_variance: float | Array, weights: Array | None = None
) -> tuple[NoiseCheck, Array | None, float]:
    """:func:`check_noise` for residuals ``r`` (n S,) and their Jacobian ``jac`` (n S, P) held
    in full, S rows per sample in sample order (a vector fit's three axes; one for a scalar fit's
    noise-weighted residuals), with per-sample ``weights`` (robust, default 1)."""
    w = np.ones(n) if weights is None else weights
    res = r.reshape(n, -1)
    rows = jac.reshape(n, res.shape[1], -1)

    def scores(sl: slice) -> Array:
        return np.asarray(np.einsum("nap,na->np", rows[sl], res[sl]) * w[sl, None])

    def normal() -> Array:
        return np.asarray(np.einsum("nap,naq,n->pq", rows, rows, w))

    return check_noise(res * np.sqrt(w)[:, None], scores, lambda sl: rows[sl], normal,
                       white_variance, jac.shape[1], w)  # fmt: skip


def fit_rows(
    p: Array, s: Samples, vector_rows: tuple[Array, Array] | None
) -> tuple[Array, RowsFunction]:
    """A fit at ``p`` of ``s`` as its covariance takes it: the residual series (N, S; not
    robust-weighted) and the Jacobian rows (slice -> (B, S, P)). ``vector_rows``: a vector fit's
    residuals (3N,) and Jacobian (3N, P), its three axes; None for a scalar fit, one series in the
    ML fit's noise-weighted form, its rows recomputed block by block."""
    if vector_rows is not None:
        raw, jac = vector_rows
        rows = jac.reshape(s.n, 3, -1)
        return raw.reshape(s.n, 3), lambda sl: rows[sl]
    r, gain = scalar_residuals_and_gain(p, s)

    def scalar_rows(sl: slice) -> Array:
        _, jac, gb = scalar_jacobian_rows(p, s.rows(sl))
        return np.asarray(jac / gb[:, None])[:, None, :]

    return (r / gain)[:, None], scalar_rows


def fit_noise_check(
    series: Array, jac_rows: RowsFunction, weights: Array, white_variance: float | Array
) -> tuple[NoiseCheck, Array | None, float]:
    """:func:`check_noise` for a fit's :func:`fit_rows` with per-sample robust ``weights`` (N,).
    Three series are a vector fit's, whose rows are held in full; one is a scalar fit's, taken
    block by block."""
    n, n_series = series.shape
    if n_series > 1:
        jac = jac_rows(slice(None))
        return rows_noise_check(series.reshape(-1), jac.reshape(n * n_series, -1), n,
                                white_variance, weights)  # fmt: skip

    def scalar_scores(rows: slice) -> Array:
        return np.asarray(jac_rows(rows)[:, 0, :] * (series[rows, 0] * weights[rows])[:, None])

    n_params = int(jac_rows(slice(0, 1)).shape[2])

    def scalar_normal() -> Array:
        total = np.zeros((n_params, n_params))
        for rows in row_blocks(n):
            jac = jac_rows(rows)[:, 0, :]
            total += (jac * weights[rows, None]).T @ jac
        return total

    return check_noise(series * np.sqrt(weights)[:, None], scalar_scores, jac_rows, scalar_normal,
                       white_variance, n_params, weights)  # fmt: skip
