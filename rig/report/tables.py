"""Plain-text parameter tables for the terminal."""

from __future__ import annotations

import numpy as np

from rig.calibration.result import ANGLE_KEYS, ANGULAR_FIELDS_UT, CalibrationResult

_LABELS = {
    "a": ("a (scale x)", ""), "b": ("b (scale y)", ""), "c": ("c (scale z)", ""),
    "x0": ("x0 offset", "uT"), "y0": ("y0 offset", "uT"), "z0": ("z0 offset", "uT"),
    "rho": ("rho", "deg"), "phi": ("phi", "deg"), "lambda": ("lambda", "deg"),
    "rot_x": ("mount rot x", "deg"), "rot_y": ("mount rot y", "deg"),
    "rot_z": ("mount rot z", "deg"),
}  # fmt: skip


def _label(name: str) -> tuple[str, str]:
    if name in _LABELS:
        return _LABELS[name]
    return name, "uT/unit"


def _fmt(value: float, sigma: float) -> tuple[str, str]:
    """Value and sigma with digits matched to the sigma (two significant digits)."""
    if not np.isfinite(sigma) or sigma <= 0:
        return f"{value:.6g}", "-"
    digits = max(0, min(9, 1 - int(np.floor(np.log10(sigma)))))
    return f"{value:.{digits}f}", f"{sigma:.{digits}f}"


def _parameter_rows(result: CalibrationResult) -> list[str]:
    """One row per parameter: label, unit, value, 1-sigma, CRLB 1-sigma, their ratio."""
    out: list[str] = []
    # Rotation error angles are reported about the fitted mounting; show the mounting itself.
    mount = None
    if result.model == "vector":
        mount = result.to_dict()["mounting"]["rotation_vector_deg"]
    for i, name in enumerate(result.names):
        label, unit = _label(name)
        scale = np.degrees(1.0) if name in ANGLE_KEYS else 1.0
        value = float(result.p[i] * scale)
        if mount is not None and name.startswith("rot_"):
            value = float(mount["xyz".index(name[-1])])
        val, sig = _fmt(value, float(result.sigma[i] * scale))
        _, crlb = _fmt(value, float(result.crlb_sigma[i] * scale))
        shown = f"{result.crlb_ratio[i]:>7.2f}" if result.crlb_sigma[i] > 0 else "-".rjust(7)
        out.append(f"  {label:<22}{unit:>8}{val:>14}{sig:>12}{crlb:>14}{shown}")
    if result.profiled is not None:
        fit = result.profiled
        for prm, v, sig, crlb_sig in zip(fit.params, fit.values, fit.sigma, fit.crlb_sigma,
                                         strict=True):  # fmt: skip
            scale = prm.shown_scale
            val, sig_text = _fmt(float(v) * scale, float(sig) * scale)
            _, crlb_text = _fmt(float(v) * scale, float(crlb_sig) * scale)
            ratio = float(sig / crlb_sig) if crlb_sig > 0 else float("nan")
            label, unit = prm.table_label, prm.shown_unit or prm.unit
            out.append(f"  {label:<22}{unit:>8}{val:>14}{sig_text:>12}{crlb_text:>14}{ratio:>7.2f}")
    return out


def calibration_table(result: CalibrationResult, source: str = "", verbose: bool = False) -> str:
    """The result as the table ``rig calibrate`` prints."""
    kind = (
        "vector (field vector known)"
        if result.model == "vector"
        else "scalar (attitude independent)"
    )
    n_ch = len(result.calibration.channels)
    lines = [
        f"Calibration of {source or 'data'}: {kind} model, method {result.method},"
        f" {result.samples} samples, {n_ch} telemetry channel{'s' if n_ch != 1 else ''}",
        "",
        f"  {'parameter':<22}{'unit':>8}{'value':>14}{'1-sigma':>12}{'CRLB 1-sigma':>14}{'ratio':>7}",
    ]
    lines += _parameter_rows(result)
    chi = result.chi2
    noise_src = (
        f"--noise-nt {result.noise_nt:g}"
        if result.noise_nt is not None
        else "estimated from residuals"
    )
    what = (
        "corrected field minus reference, per axis"
        if result.model == "vector"
        else ("corrected |h| minus reference |h|")
    )
    lines += [
        "",
        f"Residuals ({what}): rms {result.residual_rms_nt:.1f} nT, mean"
        f" {result.residual_mean_nt:.1f} nT, max {result.residual_max_nt:.1f} nT",
        f"Noise floor {result.noise_floor_nt:.1f} nT ({noise_src}; raw noise estimated"
        f" {result.noise_estimated_nt:.1f} nT): "
        + (
            f"chi2/dof {chi.reduced:.3f}, p = {chi.p_value:.3g}, {chi.verdict}"
            if result.noise_nt is not None
            else f"chi-square {chi.verdict}; give the sensor's noise (--noise-nt) to test it"
        ),
        "Angular uncertainty: "
        + ", ".join(
            f"{result.angular_uncertainty_deg(b):.3f} deg at {b:g} uT" for b in ANGULAR_FIELDS_UT
        ),
        "Correction h = W (m - o - sum_j k_j u_j), W =",
        *(
            "  [" + "  ".join(f"{v:+.6f}" for v in row) + "]"
            for row in result.calibration.correction_matrix
        ),
    ]
    if verbose:
        lines.append(f"Iterations: {result.iterations}")
    if result.warnings:
        lines += ["", "Notes and warnings:"] + [f"  - {w}" for w in result.warnings]
    return "\n".join(lines)
