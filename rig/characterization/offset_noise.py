"""How a magnetometer's offset wanders, as one model every characterization shares: white noise,
flicker and a random walk, whose Allan variance is ``a / tau + b + c tau`` (nT^2, tau in s).

A characterization averages the offset over stretches of its record (bins: a drift's time bins,
the holds around a perming shock, a thermal cycle's plateaus) and fits a linear model to the
averages. :func:`fit_bins` does it as a statistician would with noise of unknown colour:

- the covariance of the bins' averages is the model's, integrated exactly over each bin (white
  over its readings, the random walk's ``3 c`` diffusion, flicker as Gauss-Markov processes a
  decade apart whose Allan variance is flat);
- the three terms are estimated together with the coefficients by restricted maximum likelihood
  (REML: the likelihood of the residuals, which a fitted slope or step does not flatter), none
  dropped because its estimate is small: a term REML puts at 0 still adds to each sigma what
  the data cannot rule out of it (the coefficients' variance averaged over the term's values,
  weighted by the likelihood), where dropping a random walk made a drift's sigma four times
  too small;
- the coefficients by generalized least squares with that covariance; and because the noise
  itself is estimated from one record (a random walk's share of a drift from a few of its own
  steps), each sigma is widened from its Satterthwaite degrees of freedom ``nu`` (from the
  REML information of the terms off their bound of 0):
  ``sigma = se * t(0.9, nu) / z(0.9)``, the width of the Student-t 80 % interval in Gaussian
  sigmas (:data:`WIDEN_LEVEL`).

Measured against noise generated outside the model (bench/bench_characterization_audit.py, 200
records of 3 axes; docs/procedures.md): a drift's rms z 0.91-0.99 (95-96 % within 1.96 sigma)
where a random walk is mixed with white noise and flicker, a perming shift's 1.03-1.04 under
20-100 nT/sqrt(h), a thermal campaign's 0.99; with white noise alone a drift's or a shift's
sigma is about three times too wide (rms z 0.33-0.36: the walk one record cannot rule out).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

MIN_DOF = 1.0
"""The fewest degrees of freedom a sigma is widened for (t(0.9, 1) = 3.08: 2.4 times)."""


@dataclass(frozen=True)
class OffsetNoise:
    """The offset's noise: Allan variance ``white_nt2_s / tau + flicker_nt2 + walk_nt2_per_s tau``
    (nT^2 for tau in s), each term at least 0."""

    white_nt2_s: float
    flicker_nt2: float
    walk_nt2_per_s: float

    def to_dict(self) -> dict[str, float]:
        """For a result: the three terms, and each as the deviation a technician quotes."""
        return {"white_nt2_s": self.white_nt2_s, "flicker_nt2": self.flicker_nt2,
                "walk_nt2_per_s": self.walk_nt2_per_s,
                "white_nt_per_sqrt_hz": math.sqrt(2.0 * self.white_nt2_s),
                "flicker_adev_nt": math.sqrt(self.flicker_nt2),
                "walk_nt_per_sqrt_h": math.sqrt(3.0 * self.walk_nt2_per_s * 3600.0)}  # fmt: skip


@dataclass(frozen=True)
class Bins:
    """Stretches of a record the offset is averaged over: each one's first and last reading's
    time (s), and how many readings it holds at ``rate_hz`` (the readings' rate)."""

    start_s: Array
    end_s: Array
    samples: Array
    rate_hz: float

    @property
    def centre_s(self) -> Array:
        """Each bin's middle (s)."""
        return np.asarray(0.5 * (self.start_s + self.end_s))

    def parts(self) -> tuple[Array, Array, Array]:
        """The covariance of the bins' averages per unit of each term (white per nT^2 s,
        flicker per nT^2, random walk per nT^2/s), integrated over each bin."""
        dt = 1.0 / self.rate_hz
        length = np.maximum(self.end_s - self.start_s + dt, dt)  # each reading stands for dt
        start = self.start_s - 0.5 * dt
        white = np.diag(self.rate_hz / np.maximum(self.samples, 1.0))
        since = start - float(np.min(start))
        lo = np.minimum.outer(since, since)
        first = np.less_equal.outer(since, since)
        # E[W(s) W(u)] = q min(s, u): bin i before bin j gives q (start_i + L_i / 2), the same
        # bin q (start + L / 3); q = 3 c for an Allan variance c tau
        own = np.where(first, lo + 0.5 * length[:, None], lo + 0.5 * length[None, :])
        walk = 3.0 * np.where(np.eye(len(since), dtype=bool), since + length / 3.0, own)
        record = float(np.max(self.end_s) - np.min(self.start_s)) + dt
        flicker = _flicker_bins(self.centre_s, length, record)
        return white, flicker, np.asarray(walk, float)


def _ou_bins(centre_s: Array, length_s: Array, tc_s: float) -> Array:
    """The covariance of averages over bins (centres, lengths; s) of a unit-variance
    Gauss-Markov process of time constant ``tc_s``."""
    lag = np.abs(np.subtract.outer(centre_s, centre_s))
    length = 0.5 * np.add.outer(length_s, length_s)  # bins of near-equal length
    x = length / tc_s
    near = np.minimum(length - lag, 0.0)  # only bins a length or more apart use this
    apart = (np.exp(near / tc_s) + np.exp(-(length + lag) / tc_s)
             - 2.0 * np.exp(-lag / tc_s)) / x**2  # fmt: skip
    same = 2.0 * (x - 1.0 + np.exp(-x)) / x**2
    return np.asarray(np.where(lag >= length * (1 - 1e-9), apart, same), float)


def _flicker_bins(centre_s: Array, length_s: Array, record_s: float) -> Array:
    """Flicker (a flat Allan variance of 1 nT^2) as Gauss-Markov processes with time constants a
    decade apart from a tenth of the shortest bin to ten records, averaged over the bins."""
    shortest = max(float(np.min(length_s)), 1e-3)
    taus = 10.0 ** np.arange(math.floor(math.log10(shortest / 10.0)),
                             math.log10(10.0 * record_s) + 1.0)  # fmt: skip
    probe = max(record_s / 100.0, shortest)
    x = probe / taus
    # an OU process of unit variance: AVAR(tau) = (T/tau)^2 (4 e^-x - e^-2x + 2x - 3), x = tau/T
    avar = float(np.sum((4.0 * np.exp(-x) - np.exp(-2.0 * x) + 2.0 * x - 3.0) / x**2))
    return np.asarray(sum(_ou_bins(centre_s, length_s, t) for t in taus) / avar, float)


def taus_125(shortest_s: float, longest_s: float) -> Array:
    """1-2-5 averaging times from ``shortest_s`` to ``longest_s`` (s), both included."""
    decades = np.arange(math.floor(math.log10(shortest_s)), math.ceil(math.log10(longest_s)) + 1)
    taus = np.array([f * 10.0**d for d in decades for f in (1.0, 2.0, 5.0)])
    return taus[(taus >= shortest_s * (1 - 1e-6)) & (taus <= longest_s)]


HADAMARD_FLICKER = (8.0 * math.log(2.0) - 3.0 * math.log(3.0)) / (4.0 * math.log(2.0))
"""The overlapping Hadamard variance of flicker over its Allan variance (0.811); white noise
gives 1 and a random walk 1/2."""


def hadamard_noise(y_nt: Array, rate_hz: float) -> OffsetNoise:
    """A quick estimate of the model from the overlapping Hadamard variance of offsets on a
    uniform grid at ``rate_hz`` (which a drift does not touch), fitted on 1-2-5 averaging times
    up to a quarter of the record by non-negative least squares weighted by each point's
    precision: the starting point of :func:`fit_bins`."""
    import allantools
    from scipy.optimize import nnls

    y = np.asarray(y_nt, float)
    taus = taus_125(1.0 / rate_hz, max(len(y) / rate_hz / 4.0, 3.0 / rate_hz))
    tau, dev, _, _ = allantools.ohdev(y, rate=rate_hz, data_type="freq", taus=taus)
    tau = np.asarray(tau, float)
    hvar = np.asarray(dev, float) ** 2
    if len(tau) == 0:
        return OffsetNoise(float(np.var(y)) / rate_hz, 0.0, 0.0)
    model, coef = hvar, np.zeros(3)
    for _ in range(3):  # weights from the model, not from the noisy estimates
        weight = np.sqrt(len(y) / np.maximum(tau * rate_hz, 1.0)) / np.maximum(model, 1e-30)
        design = np.column_stack([1.0 / tau, np.full_like(tau, HADAMARD_FLICKER), 0.5 * tau])
        coef = nnls(design * weight[:, None], weight * hvar)[0]
        model = design @ coef
        if not np.all(model > 0):
            model = hvar
    return OffsetNoise(float(coef[0]), float(coef[1]), float(coef[2]))


def contiguous_bins(t_s: Array, count: int) -> tuple[Bins, list[npt.NDArray[np.intp]]]:
    """``count`` stretches of consecutive readings at times ``t_s`` (s), as equal as can be:
    the bins, and each one's reading indices."""
    t = np.asarray(t_s, float)
    idx = [i for i in np.array_split(np.arange(len(t)), max(1, min(count, len(t)))) if len(i)]
    rate = 1.0 / float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    bins = Bins(np.array([t[i[0]] for i in idx]), np.array([t[i[-1]] for i in idx]),
                np.array([float(len(i)) for i in idx]), rate)  # fmt: skip
    return bins, idx


@dataclass(frozen=True)
class BinFit:
    """A linear model of the bins' averages: the coefficients, their sigmas (with what the data
    cannot rule out, widened for their Satterthwaite degrees of freedom: ``se t(LEVEL, nu) /
    z(LEVEL)``) and the noise model fitted alongside."""

    coef: Array
    sigma: Array
    noise: OffsetNoise


INSIDE_SE = 0.1
"""A term whose estimate is below this many of its standard errors is taken as at 0."""
UNSEEN_GRID = np.array([0.0, 0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0])
"""Where a term at 0 is tried, in its standard errors (the likelihood weighs them)."""
WIDEN_LEVEL = 0.9
"""The one-sided level at which a sigma is widened for its degrees of freedom: the Student-t
80 % interval (widening for the 95 % one left mixed noise 15-25 % pessimistic)."""


def fit_bins(design: Array, y: Array, bins: Bins, start: OffsetNoise | None = None) -> BinFit:
    """Fit ``y`` (one axis's bin averages, nT) to ``design`` (bins x p) with the offset noise
    estimated by REML (module docstring), from the two likeliest of ``start`` and a few fixed
    mixtures (the better optimum wins). ValueError when there are no more bins than
    coefficients. The matrices are small: BLAS runs one thread (several thrash on a busy
    machine: 18 times slower beside one other process on 2 cores)."""
    with _blas_controller().limit(limits=1, user_api="blas"):
        return _fit_bins(design, y, bins, start)


@functools.cache
def _blas_controller() -> Any:
    """The process's thread-pool controller, found once (finding the BLAS libraries reads the
    process's memory map: 5 ms, a tenth of a small fit)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def _fit_bins(design: Array, y: Array, bins: Bins, start: OffsetNoise | None) -> BinFit:
    x = np.asarray(design, float)
    yv = np.asarray(y, float)
    n, p = x.shape
    if n <= p:
        raise ValueError(f"{n} bins for {p} coefficients: the noise cannot be estimated")
    parts = bins.parts()
    resid = yv - x @ np.linalg.lstsq(x, yv, rcond=None)[0]
    scale = max(float(np.mean(resid**2)), 1e-18)
    unit = np.array([scale / max(float(np.mean(np.diag(m))), 1e-300) for m in parts])
    low, high = np.log(unit * 1e-8), np.log(unit * 1e4)
    starts = [np.log(unit * np.asarray(mix)) for mix in _MIXES]
    if start is not None:
        given = np.array([start.white_nt2_s, start.flicker_nt2, start.walk_nt2_per_s])
        starts.insert(0, np.log(np.maximum(given, unit * 1e-8)))

    def cost(log_theta: Array) -> tuple[float, Array]:
        theta = np.exp(log_theta)
        try:
            value, proj = _reml(x, yv, _combine(parts, theta))
        except np.linalg.LinAlgError:  # numerically singular here: steer the optimizer away
            return 1e300, np.zeros(3)
        py = proj @ yv
        grad = np.array([float(np.sum(proj * m)) - float(py @ m @ py) for m in parts])
        return value, grad * theta

    starts = sorted((np.clip(s0, low, high) for s0 in starts), key=lambda s0: cost(s0)[0])
    from scipy import optimize  # here, not at the top: scipy's import costs every CLI 0.8 s

    fits = [optimize.minimize(cost, s0, jac=True, method="L-BFGS-B",
                              bounds=list(zip(low, high, strict=True))) for s0 in starts[:2]]  # fmt: skip
    best = min(fits, key=lambda r: float(r.fun))
    theta = np.exp(best.x)
    v = _combine(parts, theta)
    vinv = np.linalg.inv(v)
    cov = np.linalg.inv(x.T @ vinv @ x)
    left = cov @ x.T @ vinv
    proj = vinv - left.T @ x.T @ vinv
    coef = left @ yv
    # Satterthwaite: the spread of each coefficient's variance from the terms' own (REML
    # information); a term at its bound (0) has no spread to give (it is one-sided there)
    pv = [proj @ m for m in parts]
    info = np.array([[0.5 * float(np.sum(a * b.T)) for b in pv] for a in pv])
    grads = np.array([np.diag(left @ m @ left.T) for m in parts])  # terms x p
    # a term is off its bound when its estimate is a fair part of its own standard error (an
    # estimate of 1e-9 of its scatter is the bound, wherever the optimizer stopped near it)
    theta_se = np.sqrt(np.maximum(np.diag(np.linalg.pinv(info)), 0.0))
    inside = theta > INSIDE_SE * theta_se
    theta_cov = np.zeros((3, 3))
    if inside.any():
        sub = np.ix_(inside, inside)
        theta_cov[sub] = np.linalg.pinv(info[sub])
    at_fit = np.diag(cov)
    var = at_fit + _unseen_variance(x, yv, parts, theta, theta_se * ~inside, best.fun, at_fit)
    spread = np.einsum("ip,ij,jp->p", grads, theta_cov, grads)
    dof = np.clip(2.0 * var**2 / np.maximum(spread, 1e-300), MIN_DOF, 1e6)
    from scipy import stats

    widen = stats.t.ppf(WIDEN_LEVEL, dof) / stats.norm.ppf(WIDEN_LEVEL)
    return BinFit(coef, np.sqrt(var) * widen, OffsetNoise(*(float(t) for t in theta)))


def _unseen_variance(x: Array, y: Array, parts: tuple[Array, Array, Array], theta: Array,
                     reach: Array, best: float, at0: Array) -> Array:  # fmt: skip
    """What the terms at 0 that the data cannot rule out add to each coefficient's variance:
    per such term (``reach`` its standard error, 0 for the others) the coefficients' variance
    averaged over the term's values from 0 to six standard errors (:data:`UNSEEN_GRID`), weighted
    by the restricted likelihood (a flat prior on the term), less the variance at the fit
    (``at0``, where -2 log the likelihood is ``best``)."""
    extra = np.zeros_like(at0)
    for k in np.flatnonzero(reach > 0):
        weights, variances = [], []
        for f in UNSEEN_GRID:
            trial = theta.copy()
            trial[k] += f * reach[k]
            v = _combine(parts, trial)
            weights.append(math.exp(-0.5 * (_reml(x, y, v)[0] - best)))
            variances.append(_coef_variance(x, v))
        w = np.asarray(weights)
        extra += np.maximum(w @ np.asarray(variances) / w.sum() - at0, 0.0)
    return np.asarray(extra, float)


def _coef_variance(x: Array, v: Array) -> Array:
    """The GLS coefficients' variances for the noise covariance ``v``."""
    return np.asarray(np.diag(np.linalg.inv(x.T @ np.linalg.solve(v, x))), float)


_MIXES = ((1.0, 1e-3, 1e-3), (0.3, 0.3, 0.3), (1e-3, 1e-3, 1.0), (1e-3, 1.0, 1e-3))
"""Starting mixtures of the three terms (in units of the residuals' scatter)."""


def _combine(parts: tuple[Array, Array, Array], theta: Array) -> Array:
    """The bins' covariance for the terms ``theta``, with a jitter of 1e-9 of its mean variance
    on the diagonal (a walk or flicker alone is near singular over many bins)."""
    v = np.asarray(sum(t * m for t, m in zip(theta, parts, strict=True)), float)
    return v + 1e-9 * float(np.mean(np.diag(v))) * np.eye(len(v))


def _reml(x: Array, y: Array, v: Array) -> tuple[float, Array]:
    """-2 log restricted likelihood (up to a constant) and the REML projection ``P``."""
    chol = np.linalg.cholesky(v)
    vinv = np.linalg.inv(v)
    xtvx = x.T @ vinv @ x
    left = np.linalg.solve(xtvx, x.T @ vinv)
    proj = vinv - vinv @ x @ left
    value = 2.0 * float(np.sum(np.log(np.diag(chol)))) + float(np.linalg.slogdet(xtvx)[1])
    return value + float(y @ proj @ y), np.asarray(proj, float)


def joint_z(chi2: float, dof: int) -> float:
    """The two-sided normal z of a chi-square statistic with ``dof`` degrees of freedom (inf when
    its p-value underflows): how many sigma a joint shift is from none."""
    from scipy import stats

    p = float(stats.chi2.sf(chi2, dof))
    return float(stats.norm.isf(p / 2.0)) if p > 0 else math.inf
