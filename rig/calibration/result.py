"""A calibration result: parameters, uncertainty, the Cramer-Rao bound, residuals and warnings."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.typing as npt

from rig.calibration.correlated import NoiseCheck, fit_noise_check, fit_rows
from rig.calibration.estimate import Estimate, FilterHistory, delta_method
from rig.calibration.hold_means import hold_noise
from rig.calibration.params import Array, Calibration, Springmann
from rig.calibration.residuals import (
    AXES,
    Samples,
    calibration_from_p,
    k_start,
    parameter_names,
    scalar_normal_equations,
    vector_residuals,
)
from rig.calibration.solver import axis_variances, covariance_from_normal
from rig.calibration.stats import chi2_sf
from rig.errors import CalibrationError

if TYPE_CHECKING:
    from rig.calibration.profiled import ProfileFit  # only a fit with delays or temperature

ModelKind = Literal["scalar", "vector"]
ANGLE_KEYS = frozenset({"rho", "phi", "lambda", "rot_x", "rot_y", "rot_z"})
CORRELATION_WARN = 0.9
"""Parameter pairs correlated more strongly than this get a warning."""
ANGULAR_FIELDS_UT = (20.0, 50.0)
"""Field strengths for the angular uncertainty (Springmann-Cutler Tables 3-4)."""
SPRINGMANN_JSON = {
    "a": "a", "b": "b", "c": "c", "x0": "x0_ut", "y0": "y0_ut", "z0": "z0_ut",
    "rho": "rho_deg", "phi": "phi_deg", "lambda": "lambda_deg",
}  # fmt: skip


def springmann_json(sp: Springmann) -> dict[str, float]:
    """The result file's ``springmann`` block: the nine values under their :data:`SPRINGMANN_JSON`
    keys, angles in degrees."""
    return {SPRINGMANN_JSON[k]: float(math.degrees(v) if k in ANGLE_KEYS else v)
            for k, v in zip(SPRINGMANN_JSON, sp.as_vector(), strict=True)}  # fmt: skip


Verdict = Literal[
    "consistent",
    "above noise floor",
    "below noise floor",
    "not tested (noise estimated from these residuals)",
    "degenerate fit (parameters not determined by the data)",
]
"""The chi-square verdict on the residuals (see :func:`_chi_square`)."""


@dataclass(frozen=True)
class ChiSquareTest:
    """Residuals against a noise floor: statistic, degrees of freedom, p-value and a verdict."""

    statistic: float
    dof: int
    p_value: float
    verdict: Verdict

    @property
    def reduced(self) -> float:
        """Statistic per degree of freedom (1 when residuals match the noise floor)."""
        return self.statistic / self.dof


@dataclass(frozen=True)
class CalibrationResult:
    """Everything a fit produces. Angles in ``p`` are rad; units at the boundary in :meth:`to_dict`."""

    model: ModelKind
    method: str
    samples: int
    calibration: Calibration
    names: tuple[str, ...]
    p: Array
    covariance: Array
    crlb: Array
    residuals_nt: Array
    noise_nt: float | None
    noise_estimated_nt: float
    noise_floor_nt: float
    chi2: ChiSquareTest
    warnings: tuple[str, ...]
    iterations: int
    history: FilterHistory | None = None
    profiled: ProfileFit | None = None
    temperature_ref: float | None = None
    noise_check: NoiseCheck | None = None
    """The residuals' whiteness and tails; when correlated, ``covariance`` and ``crlb`` hold for
    that noise (ADR 0025)."""

    @property
    def sigma(self) -> Array:
        """1-sigma of ``p`` from the estimator's own covariance."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def crlb_sigma(self) -> Array:
        """1-sigma Cramer-Rao bound of ``p`` at the estimate."""
        return np.sqrt(np.maximum(np.diag(self.crlb), 0.0))

    def profiled_values(self, group: str) -> dict[str, float]:
        """Profiled parameters of one group (``delay_s``: s per channel; ``temperature``:
        ``scale_per_k`` in 1/K); empty when the fit had none."""
        if self.profiled is None:
            return {}
        return {prm.key: float(v) for prm, v in zip(self.profiled.params, self.profiled.values,
                                                    strict=True) if prm.group == group}  # fmt: skip

    def unexported_model(self, who: str) -> list[str]:
        """One line per part of the model ``who`` (an export without delays or a temperature
        scale) leaves out, naming the value: a flight computer without it applies a different
        correction from the one fitted."""
        out = []
        for ch, tau in self.profiled_values("delay_s").items():
            out.append(f"left out: channel '{ch}' delay {tau:+.4f} s ({who} applies currents"
                       " undelayed): feed it the current that much earlier or later")  # fmt: skip
        scale = self.profiled_values("temperature").get("scale_per_k")
        if scale is not None:
            out.append(f"left out: temperature scale coefficient {scale * 1e6:+.1f} ppm/K about"
                       f" {self.temperature_ref:g} ({who} has no such term)")  # fmt: skip
        return out

    @property
    def crlb_ratio(self) -> Array:
        """Reported sigma over the Cramer-Rao sigma (1 = efficient)."""
        return self.sigma / np.maximum(self.crlb_sigma, 1e-300)

    @property
    def residual_rms_nt(self) -> float:
        """Root mean square of the corrected-field residuals (nT)."""
        return float(np.sqrt(np.mean(self.residuals_nt**2)))

    @property
    def residual_rms_axes_nt(self) -> list[float] | None:
        """A vector fit's residual rms per DUT axis (nT, x y z); None for a scalar fit."""
        n = self.residuals_nt.size // 3
        if self.model != "vector" or self.residuals_nt.size != 3 * n or n == 0:
            return None
        return [float(v) for v in np.sqrt(np.mean(self.residuals_nt.reshape(n, 3) ** 2, axis=0))]

    @property
    def noise_axes_nt(self) -> list[float] | None:
        """A vector fit's noise per DUT axis as its sigmas take it (nT, x y z): the residual rms,
        scaled to the noise the hold means see when the sigmas come from them (issue 55: aliased
        mains ripple in the samples, not in the means); None for a scalar fit."""
        axes = self.residual_rms_axes_nt
        ratio = () if self.noise_check is None else self.noise_check.hold_variance_ratio
        if axes is None or len(ratio) != 3:
            return axes
        return [float(v * math.sqrt(r)) for v, r in zip(axes, ratio, strict=True)]

    @property
    def residual_mean_nt(self) -> float:
        """Mean corrected-field residual (nT)."""
        return float(np.mean(self.residuals_nt))

    @property
    def residual_max_nt(self) -> float:
        """Largest absolute corrected-field residual (nT)."""
        return float(np.max(np.abs(self.residuals_nt)))

    def angular_uncertainty_deg(self, field_ut: float) -> float:
        """Direction uncertainty ``atan(rms / |B|)`` (deg) at field strength ``field_ut``."""
        return math.degrees(math.atan(self.residual_rms_nt / 1000.0 / field_ut))

    def correlations(self, threshold: float = CORRELATION_WARN) -> list[tuple[str, str, float]]:
        """Parameter pairs with ``|correlation| > threshold``, strongest first."""
        sd = self.sigma
        corr = correlation_matrix(self.covariance)
        pairs = [
            (self.names[i], self.names[j], float(corr[i, j]))
            for i in range(len(sd))
            for j in range(i + 1, len(sd))
            if abs(corr[i, j]) > threshold
        ]
        return sorted(pairs, key=lambda t: -abs(t[2]))

    def value(self, name: str) -> float:
        """Parameter by name, in user units (deg for angles)."""
        i = self.names.index(name)
        return float(np.degrees(self.p[i]) if name in ANGLE_KEYS else self.p[i])

    def to_dict(self) -> dict[str, Any]:
        """The result file (contract): see README, 'Result file'."""
        cal = self.calibration
        sp = cal.springmann
        cr = cal.crassidis
        out: dict[str, Any] = {
            "model": self.model,
            "method": self.method,
            "samples": self.samples,
            "channels": list(cal.channels),
            "correction": {
                "matrix": cal.correction_matrix.tolist(),
                "offset_ut": cal.offset_ut.tolist(),
                "k_ut_per_unit": {
                    ch: cal.k_ut_per_unit[j].tolist() for j, ch in enumerate(cal.channels)
                },
                "equation": "h = matrix @ (m - offset_ut - sum_j k_j * u_j)",
            },
            "springmann": springmann_json(sp),
            "crassidis": {
                "b_ut": cr.b_ut.tolist(),
                "D": cr.d_matrix.tolist(),
                **self._crassidis_sigma(),
            },
            "covariance": {"names": list(self.names), "matrix": self.covariance.tolist()},
            "mounting": self._mounting(),
            "sigma": self._by_group(self.sigma),
            "crlb_sigma": self._by_group(self.crlb_sigma),
            "crlb_ratio": self._by_group(self.crlb_ratio, ratio=True),
            "residual_rms_nt": self.residual_rms_nt,
            **(
                {
                    "residual_rms_axes_nt": self.residual_rms_axes_nt,
                    "noise_axes_nt": self.noise_axes_nt,
                }
                if self.residual_rms_axes_nt is not None
                else {}
            ),
            "residual_mean_nt": self.residual_mean_nt,
            "residual_max_nt": self.residual_max_nt,
            "noise_nt": self.noise_nt,
            "noise_estimated_nt": self.noise_estimated_nt,
            "noise_floor_nt": self.noise_floor_nt,
            "chi2": {
                "statistic": self.chi2.statistic,
                "dof": self.chi2.dof,
                "reduced": self.chi2.reduced,
                "p_value": self.chi2.p_value,
                "verdict": self.chi2.verdict,
            },
            "angular_uncertainty_deg": {
                f"{b:g}_ut": self.angular_uncertainty_deg(b) for b in ANGULAR_FIELDS_UT
            },
            "correlations": [{"a": a, "b": b, "r": r} for a, b, r in self.correlations()],
            "warnings": list(self.warnings),
            "iterations": self.iterations,
        }
        self._add_extras(out)
        return out

    def _add_extras(self, out: dict[str, Any]) -> None:
        """The profiled parameters (delays, temperature) with their sigma, the temperature
        reference, a filter's summary and the residuals' whiteness, into the result file ``out``."""
        if self.noise_check is not None:
            out["residual_whiteness"] = self.noise_check.to_dict()
        if self.profiled is not None:
            fit = self.profiled
            for prm, v, sig, crlb in zip(fit.params, fit.values, fit.sigma, fit.crlb_sigma,
                                         strict=True):  # fmt: skip
                out.setdefault(prm.group, {})[prm.key] = float(v)
                out["sigma"].setdefault(prm.group, {})[prm.key] = float(sig)
                out["crlb_sigma"].setdefault(prm.group, {})[prm.key] = float(crlb)
        if self.temperature_ref is not None:
            out.setdefault("temperature", {})["reference"] = self.temperature_ref
        if self.history is not None:
            nis = self.history.nis[np.isfinite(self.history.nis)]
            out["filter"] = {
                "updates": int(nis.size),
                "mean_nis": float(np.mean(nis)) if nis.size else None,
                "recorded_rows": int(self.history.index.size),
            }

    def _crassidis_sigma(self) -> dict[str, Any]:
        """1-sigma of the Crassidis ``b`` (uT) and ``D`` (eq. 11), by the delta method."""
        if self.model != "scalar":
            return {}

        def to_bd(p: Array) -> Array:
            cr = calibration_from_p(p, self.calibration.channels).crassidis
            return np.concatenate([cr.b_ut, cr.d_matrix.reshape(-1)])

        try:
            _, cov = delta_method(to_bd, self.p, self.covariance, self.method)
        except CalibrationError:  # an invalid ellipsoid has no sigma to report
            return {}
        sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        return {"b_sigma_ut": sig[:3].tolist(), "D_sigma": sig[3:].reshape(3, 3).tolist()}

    def _mounting(self) -> dict[str, Any]:
        if self.model == "scalar":
            return {"observable": False}
        from scipy.spatial.transform import Rotation

        rot = Rotation.from_matrix(self.calibration.rotation)
        return {
            "observable": True,
            "rotation_matrix": self.calibration.rotation.tolist(),
            "rotation_vector_deg": np.degrees(rot.as_rotvec()).tolist(),
            "angle_deg": float(np.degrees(rot.magnitude())),
        }

    def reported(self) -> Array:
        """The values the result reports, flat in the ``sigma`` block's order and units
        (:meth:`grouped` gives them their shape): the nine Springmann values (angles in degrees),
        the current-to-bias coefficients (uT per unit) and, for a vector fit, the mounting
        rotation vector (deg)."""
        cal = self.calibration
        values = list(springmann_json(cal.springmann).values())
        values += [float(v) for j in range(len(cal.channels)) for v in cal.k_ut_per_unit[j]]
        if self.model == "vector":
            values += [float(v) for v in self._mounting()["rotation_vector_deg"]]
        return np.asarray(values, float)

    def reported_sigma(self) -> Array:
        """1-sigma of :meth:`reported`, same order and units."""
        block = self._by_group(self.sigma)
        values = list(block["springmann"].values())
        values += [v for ch in self.calibration.channels for v in block["k_ut_per_unit"][ch]]
        return np.asarray(values + list(block.get("mounting_deg", [])), float)

    def grouped(self, values: Array) -> dict[str, Any]:
        """Flat values in :meth:`reported`'s order and units given the result file's groups (the
        ``sigma`` block's shape)."""
        v = [float(x) for x in np.asarray(values, float)]
        channels = self.calibration.channels
        out: dict[str, Any] = {"springmann": dict(zip(SPRINGMANN_JSON.values(), v[:9], strict=True)),
                               "k_ut_per_unit": {ch: v[9 + 3 * j: 12 + 3 * j]
                                                 for j, ch in enumerate(channels)}}  # fmt: skip
        if self.model == "vector":
            out["mounting_deg"] = v[9 + 3 * len(channels) : 12 + 3 * len(channels)]
        return out

    def _by_group(self, values: Array, *, ratio: bool = False) -> dict[str, Any]:
        def conv(name: str, v: float) -> float:
            return float(math.degrees(v) if (name in ANGLE_KEYS and not ratio) else v)

        named = dict(zip(self.names, values, strict=True))
        out: dict[str, Any] = {
            "springmann": {SPRINGMANN_JSON[k]: conv(k, named[k]) for k in SPRINGMANN_JSON},
            "k_ut_per_unit": {
                ch: [float(named[f"k[{ch}].{ax}"]) for ax in AXES]
                for ch in self.calibration.channels
            },
        }
        if self.model == "vector":
            out["mounting_deg"] = [conv(k, named[k]) for k in ("rot_x", "rot_y", "rot_z")]
        return out


def _chi_square(
    weighted_residuals: Array, noise: float, n_params: int, tested: bool, degenerate: bool
) -> ChiSquareTest:
    """The residuals against the noise. ``tested`` False: the noise was estimated from these same
    residuals (chi2/dof is 1 by construction), so nothing is tested. ``degenerate``: parameters
    the data do not determine; small residuals then say nothing about the calibration."""
    dof = max(int(weighted_residuals.size) - n_params, 1)
    stat = float(np.sum((weighted_residuals / noise) ** 2))
    p_value = chi2_sf(stat, dof)
    verdict: Verdict = "consistent"
    if p_value < 1e-3:
        verdict = "above noise floor"
    elif p_value > 1 - 1e-3:
        verdict = "below noise floor"
    if not tested:
        verdict = "not tested (noise estimated from these residuals)"
    if degenerate:
        verdict = "degenerate fit (parameters not determined by the data)"
    return ChiSquareTest(stat, dof, p_value, verdict)


DEGENERATE_CORRELATION = 0.999
"""|correlation| between two parameters above which the fit does not determine them."""


def correlation_matrix(covariance: Array) -> Array:
    """The parameters' correlations (1 on the diagonal); a parameter a method holds fixed
    (variance 0) correlates with nothing (0, also on its diagonal)."""
    sd = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    scale = np.outer(sd, sd)
    return np.asarray(np.divide(covariance, scale, out=np.zeros_like(scale), where=scale > 0))


def summarize(
    est: Estimate, s: Samples, noise_nt: float | None, extra_warnings: tuple[str, ...] = ()
) -> CalibrationResult:
    """Assemble a :class:`CalibrationResult` from an estimate and its data."""
    vector = est.rotation_ref is not None
    names = parameter_names(s.channels, vector=vector)
    cal = calibration_from_p(est.p, s.channels, rotation_ref=est.rotation_ref)
    robust_w = np.ones(s.n) if est.sample_weights is None else est.sample_weights
    if vector:
        assert est.rotation_ref is not None and s.field_ut is not None
        raw, jac = vector_residuals(est.p, s, est.rotation_ref)
        weighted = raw * np.repeat(np.sqrt(robust_w), 3)
        fisher = jac.T @ jac
        vector_rows: tuple[Array, Array] | None = (raw, jac)
        corrected = cal.apply(s.measured_ut, s.telemetry if s.n_channels else None) - s.field_ut
        residuals_nt = 1000.0 * corrected.reshape(-1)
        floor_gain = float(np.linalg.norm(cal.correction_matrix) / np.sqrt(3.0))
    else:
        # One pass: residuals, noise gains and the Fisher information J^T diag(1/gain^2) J.
        r = np.empty(s.n)
        ne = scalar_normal_equations(est.p, s, noise_weighted=True, residuals_out=r)
        assert ne.gain is not None
        fisher, gain = ne.jtj, ne.gain
        vector_rows = None
        weighted = r * np.sqrt(robust_w) / gain
        residuals_nt = 1000.0 * r
        floor_gain = float(np.sqrt(np.mean(gain**2)))
    n_eff = float(np.sum(robust_w > 0)) * (3 if vector else 1)
    fitted = np.diag(est.covariance) > 0  # one held at its nominal value takes no dof
    n_fitted = int(np.count_nonzero(fitted))
    sigma_hat = float(np.sqrt(np.sum(weighted**2) / max(n_eff - n_fitted, 1.0)))
    noise_ut = sigma_hat if noise_nt is None else noise_nt / 1000.0
    check, covariance, crlb = _noise_model(est, s, vector_rows, weighted, sigma_hat, noise_nt,
                                           fisher, fitted)  # fmt: skip
    corr = correlation_matrix(est.covariance)
    np.fill_diagonal(corr, 0.0)  # (a held parameter's is 0 already: never taken for -1)
    degenerate = bool(np.max(np.abs(corr)) > DEGENERATE_CORRELATION) if est.p.size > 1 else False
    chi = _chi_square(weighted, noise_ut, n_fitted, noise_nt is not None, degenerate)
    result = CalibrationResult(
        model="vector" if vector else "scalar",
        method=est.method,
        samples=s.n,
        calibration=cal,
        names=names,
        p=est.p,
        covariance=covariance,
        crlb=crlb,
        residuals_nt=residuals_nt,
        noise_nt=noise_nt,
        noise_estimated_nt=1000.0 * sigma_hat,
        noise_floor_nt=1000.0 * noise_ut * floor_gain,
        chi2=chi,
        warnings=(),
        iterations=est.iterations,
        history=est.history,
        noise_check=check,
    )
    warnings = list(extra_warnings) + list(est.notes) + check.notes(est.sample_weights is not None)
    warnings += _warnings(result, s, est, noise_nt)
    return _replace_warnings(result, tuple(warnings))


NEAR_ZERO = 0.05
"""A channel value counts as near zero below this fraction of the channel's largest |value|."""


def _offset_channel_advice(channel: str, u: Array) -> str:
    """Why an offset and the coefficient of ``channel`` (values ``u``) correlate, as the data show
    it: the channel's mean is large against its spread (the offset and ``k u`` then move alike)."""
    top = float(np.max(np.abs(u)))
    near = np.abs(u) <= NEAR_ZERO * top
    spread = f"mean {float(np.mean(u)):.3g}, standard deviation {float(np.std(u)):.3g}"
    if not np.any(near):
        return (
            f"channel '{channel}' never returns near zero (min |u| = {float(np.min(np.abs(u))):.3g},"
            f" {spread}); record a segment with it at zero to separate offset and coefficient"
        )
    return (
        f"channel '{channel}' is near zero in {100 * float(np.mean(near)):.0f} % of the samples"
        f" ({spread}); more samples with it at zero (or of the opposite sign) separate offset and"
        " coefficient"
    )


def _noise_model(
    est: Estimate,
    s: Samples,
    vector_rows: tuple[Array, Array] | None,
    weighted: Array,
    sigma_hat: float,
    noise_nt: float | None,
    fisher: Array,
    fitted: npt.NDArray[np.bool_],
) -> tuple[NoiseCheck, Array, Array]:
    """The residuals' whiteness test, the covariance (from the hold means' scatter where the
    samples are numbered by hold, else HAC sigmas when correlated) and the
    Cramer-Rao bound for the same noise (white, or an AR model of it) (ADR 0025), over the
    parameters the method fits: one it holds at its nominal value (variance 0) is known, so it
    neither takes a degree of freedom nor loosens the others' bound (a held-k vector fit's offsets
    had read 0.47 of a bound computed with k free); ``fitted``: which parameters it fits;
    ``noise_nt``: the raw noise given for the bound (nT; None: estimated, ``sigma_hat``, uT)."""
    # a vector fit's axes each have their own residual variance (as its covariance, ADR 0025)
    variance = (sigma_hat**2 if vector_rows is None
                else axis_variances(weighted, int(np.count_nonzero(fitted))))  # fmt: skip
    weights = np.ones(s.n) if est.sample_weights is None else est.sample_weights
    series, jac_rows = fit_rows(est.p, s, vector_rows)
    check, info, ratio = fit_noise_check(series, jac_rows, weights, variance)
    held = (None if s.holds is None
            else hold_noise(series, jac_rows, weights, s.holds, variance, fitted))  # fmt: skip
    if held is not None:  # the noise the hold means see (issue 55)
        check = dataclasses.replace(
            check, inflation=held.factors(check.inflation), holds=held.holds,
            hold_variance_ratio=tuple(float(v) for v in held.variance_ratio),
            between_holds=held.between_bandwidth,
        )  # fmt: skip
    covariance = est.covariance * np.outer(check.inflation, check.inflation)
    if held is not None and noise_nt is None:
        return check, covariance, held.crlb
    noise_ut = sigma_hat if noise_nt is None else noise_nt / 1000.0
    normal, scale = (fisher, noise_ut**2) if info is None else (info, noise_ut**2 * ratio)
    crlb = np.zeros_like(normal)
    crlb[np.ix_(fitted, fitted)] = covariance_from_normal(normal[np.ix_(fitted, fitted)], scale)
    return check, covariance, crlb


def _replace_warnings(result: CalibrationResult, warnings: tuple[str, ...]) -> CalibrationResult:
    from dataclasses import replace

    return replace(result, warnings=warnings)


def _warnings(
    result: CalibrationResult, s: Samples, est: Estimate, noise_nt: float | None
) -> list[str]:
    out: list[str] = []
    if result.model == "scalar":
        out.append(
            "scalar (attitude-independent) calibration: the mounting rotation is unobservable;"
            " the correction is in the sensor's own frame with x as reference axis"
        )
    if noise_nt is not None and result.chi2.verdict == "above noise floor":
        out.append(
            f"residuals exceed the {noise_nt:g} nT noise floor (chi2/dof {result.chi2.reduced:.2f}):"
            " the model misses something (a telemetry channel, a delay, a nonlinear sensor)"
        )
    if noise_nt is not None and result.chi2.verdict == "below noise floor":
        out.append(
            f"residuals are below the {noise_nt:g} nT noise floor (chi2/dof"
            f" {result.chi2.reduced:.2f}): --noise-nt overstates the noise"
        )
    if est.sample_weights is not None:
        n_low = int(np.sum(est.sample_weights < 0.5))
        out.append(f"robust reweighting down-weighted {n_low} of {s.n} samples below 0.5")
    ks = k_start(result.model == "vector")
    for a, b, r in result.correlations()[:6]:
        msg = f"parameters {a} and {b} are correlated (r = {r:+.3f})"
        k_name = b if b.startswith("k[") else a if a.startswith("k[") else None
        other = a if k_name == b else b
        if k_name is not None and other in ("x0", "y0", "z0"):
            ch = k_name[2 : k_name.index("]")]
            msg += ": " + _offset_channel_advice(ch, s.telemetry[:, s.channels.index(ch)])
        elif result.names.index(a) < ks and result.names.index(b) < ks:
            msg += ": cover more field directions and magnitudes"
        out.append(msg)
    return out
