"""The report's figures of a calibration (on the samples it was fitted on) and of a live
calibration's convergence."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from rig.analysis import apply_correction, selected_data
from rig.calibration.record import CalibrationRecord, LiveBlock
from rig.calibration.targets import SIGMA_TARGETS, group_of
from rig.errors import RigError
from rig.report.scaling import mark_outliers, robust_limits, robust_log_limits
from rig.steps import field_kinds
from rig.store import safe_files
from rig.store.run_store import RunReader

Array = npt.NDArray[np.float64]
Titled = tuple[str, Any]
"""(title, matplotlib figure)."""


def calibration_series(
    reader: RunReader, meta: dict[str, Any], res: CalibrationRecord
) -> dict[str, Array] | None:
    """Time series for the plots, on the samples the calibration was fitted on (its stored
    selection): DUT raw and corrected magnitude, reference magnitude, residual (nT)."""

    channels = list(res.channels)
    try:
        s, t, *_ = selected_data(reader, res, field_kinds=field_kinds())
    except RigError:
        return None
    corrected = apply_correction(res.correction, s.measured_ut, s.telemetry, channels)
    return {
        "t": t - float(meta.get("start_monotonic", t[0])),
        "raw": np.linalg.norm(s.measured_ut, axis=1),
        "corrected": np.linalg.norm(corrected, axis=1),
        "reference": s.field_magnitude_ut,
        "residual_nt": 1000.0 * (corrected - (s.field_ut if s.field_ut is not None else 0.0)),
        "field": s.field_ut if s.field_ut is not None else np.zeros((s.n, 3)),
        "telemetry": s.telemetry,
        "channels": np.array(channels, dtype=object),
    }


def calibration_figures(
    reader: RunReader, meta: dict[str, Any], name: str, res: CalibrationRecord, plt: Any
) -> list[Titled]:
    """Magnitudes, residuals over time with the load currents, residual histogram and the
    coverage of field directions, of the calibration ``name``."""
    series = calibration_series(reader, meta, res)
    if series is None:
        return []
    return [_magnitudes(series, name, plt), _residuals(series, plt), _histogram(series, plt),
            _coverage(series, plt)]  # fmt: skip


def _magnitudes(series: dict[str, Array], name: str, plt: Any) -> Titled:
    t = series["t"]
    fig, ax = plt.subplots(figsize=(9, 3.6))
    ax.plot(t, series["raw"], ".", ms=2, label="DUT raw |m|")
    ax.plot(t, series["corrected"], ".", ms=2, label="DUT calibrated |h|")
    ax.plot(t, series["reference"], "-", lw=0.8, label="reference |h|")
    ax.set_xlabel("time since start (s)")
    ax.set_ylabel("field magnitude (uT)")
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    return f"Field magnitude: raw, calibrated ('{name}') and reference", fig


def _residuals(series: dict[str, Array], plt: Any) -> Titled:
    t = series["t"]
    fig, ax = plt.subplots(figsize=(9, 3.6))
    limits = robust_limits(series["residual_nt"])
    for i, axis in enumerate("xyz"):
        ax.plot(t, series["residual_nt"][:, i], ".", ms=2, label=f"residual {axis}")
    mark_outliers(ax, np.repeat(t, 3), series["residual_nt"].ravel(), limits, "nT")
    ax.set_xlabel("time since start (s)")
    ax.set_ylabel("calibrated minus reference (nT)")
    ax.grid(alpha=0.3)
    if series["telemetry"].size:
        ax2 = ax.twinx()
        for j, ch in enumerate(series["channels"]):
            ax2.plot(t, series["telemetry"][:, j], "-", lw=0.8, alpha=0.6, label=f"{ch} (A)")
        ax2.set_ylabel("load current (A)")
        ax2.legend(loc="upper right", fontsize=8)
    ax.legend(loc="upper left", fontsize=8)
    return "Residual over time with the load currents", fig


def _histogram(series: dict[str, Array], plt: Any) -> Titled:
    fig, ax = plt.subplots(figsize=(6, 3.4))
    r = series["residual_nt"].ravel()
    limits = robust_limits(r)
    ax.hist(np.clip(r, limits.lo, limits.hi), bins=60, range=(limits.lo, limits.hi),
            color="tab:blue", alpha=0.8)  # fmt: skip
    ax.set_xlabel("residual per axis (nT)")
    ax.set_ylabel("samples")
    beyond = (f"; {limits.outside} beyond the axis, counted in its end bins (most extreme"
              f" {limits.extreme:.0f} nT)" if limits.outside else "")  # fmt: skip
    ax.set_title(f"rms {np.sqrt(np.mean(r**2)):.1f} nT, mean {np.mean(r):.1f} nT{beyond}",
                 fontsize=9)  # fmt: skip
    return "Residual histogram", fig


def _coverage(series: dict[str, Array], plt: Any) -> Titled:
    f = series["field"]
    f = f[np.linalg.norm(f, axis=1) > 2.0]  # a null field has no direction
    d = f / np.maximum(np.linalg.norm(f, axis=1), 1e-12)[:, None]
    fig = plt.figure(figsize=(7, 3.6))
    ax = fig.add_subplot(111, projection="mollweide")
    lon = np.arctan2(d[:, 1], d[:, 0])
    lat = np.arcsin(np.clip(d[:, 2], -1, 1))
    sc = ax.scatter(lon, lat, c=np.linalg.norm(f, axis=1), s=4, cmap="viridis")
    ax.grid(alpha=0.4)
    ax.tick_params(labelsize=7)
    fig.colorbar(sc, ax=ax, label="|B| (uT)", shrink=0.8)
    ax.set_title("applied field directions (cage frame, longitude = atan2(By, Bx))", fontsize=9)
    return "Coverage of applied field directions", fig


MAX_HISTORY_BYTES = 64 << 20
"""A live calibration's history file larger than this is not plotted."""


def read_history(path: Path) -> tuple[list[str], Array] | None:
    """A live calibration's history CSV: header and rows (elapsed s, samples, p..., sigma...);
    None when missing, unreadable, a link or not a regular file."""

    try:
        text = safe_files.read_text(path, MAX_HISTORY_BYTES)
        rows = list(csv.reader(io.StringIO(text, newline="")))
        return rows[0], np.array(rows[1:], float).reshape(len(rows) - 1, len(rows[0]))
    except (OSError, ValueError, IndexError, safe_files.UnsafeFileError):
        return None


def convergence_figure(folder: Path, live: LiveBlock, plt: Any) -> Any:
    """One panel per target group: each parameter's 1-sigma against time, the plan's forecast
    dotted (when the run had one), the target dashed, the stop marked."""

    name = live.history_file
    if not name or "/" in name or "\\" in name or name.startswith("."):
        return None  # a file of the run folder itself, never a path elsewhere
    table = read_history(folder / name)
    if table is None or table[1].shape[0] == 0:
        return None
    header, rows = table
    sigma_cols = [(i, h[len("sigma_") :]) for i, h in enumerate(header) if h.startswith("sigma_")]
    groups = [g for g in SIGMA_TARGETS if any(group_of(n)[0] == g for _, n in sigma_cols)]
    fig, axes = plt.subplots(1, len(groups), figsize=(3.0 * len(groups), 3.2), squeeze=False)
    t = rows[:, 0]
    for ax, group in zip(axes[0], groups, strict=True):
        drawn: list[Array] = []
        for i, name in sigma_cols:
            g, factor = group_of(name)
            if g == group:
                drawn.append(factor * rows[:, i])
                ax.semilogy(t, drawn[-1], lw=1.0, label=name)
        if (
            f"forecast_{group}" in header
        ):  # the plan's forecast at this run's noise (no forecast: NaN)
            ax.semilogy(t, rows[:, header.index(f"forecast_{group}")], ":", color="0.3", lw=1.2,
                        label="forecast (plan)")  # fmt: skip
        target = live.targets.get(group)
        if target:
            ax.axhline(target, color="k", ls="--", lw=1.0, label="target")
        # the axis over the bulk of the sigmas and the target; a spike beyond it counted
        limits = robust_log_limits(np.concatenate(drawn) if drawn else [], [target or np.nan])
        ax.set_ylim(limits.lo, limits.hi)
        if limits.outside:
            ax.text(0.02, 0.02, f"{limits.outside} beyond the axis (most extreme"
                    f" {limits.extreme:.3g})", transform=ax.transAxes, fontsize=6, color="red")  # fmt: skip
        ax.axvline(live.elapsed_s or float(t[-1]), color="tab:red", lw=0.8, alpha=0.7)
        ax.set_title(SIGMA_TARGETS[group], fontsize=8)
        ax.set_xlabel("time in step (s)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=6, loc="upper right")
    axes[0][0].set_ylabel("1-sigma")
    fig.suptitle(live.stopped, fontsize=9)
    return fig
