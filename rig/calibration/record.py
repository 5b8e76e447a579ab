"""A stored calibration result, typed: what the ``calibrate`` and ``live_calibrate`` steps record
and the report, ``rig show`` and the live page read.

The store keeps the result as a JSON mapping (the result file contract, README 'Result file');
:meth:`CalibrationRecord.from_dict` and :meth:`CalibrationRecord.to_dict` are the one conversion.
Keys this record does not name are kept as they were, so a stored value reads back unchanged and
old run folders (no ``selection``) still read.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class SampleSelection:
    """Which recorded samples a calibration was fitted on: enough to select them again."""

    steps: tuple[str, ...]
    """The steps whose settled samples were used (names; resolved, never 'every field step')."""
    settle_s: float
    """Samples within this time (s) after a field or load change were left out."""
    telemetry: tuple[str, ...]
    """Load channels fitted (their current-to-bias coefficients)."""
    dut: str
    """The DUT's device name."""
    reference: str
    """The reference magnetometer's device name."""
    unresolved: int = 0
    """Samples left out: the field moved faster than the reference resolves."""
    misdated: int = 0
    """Samples left out: they moved at a hold's edge while the reference held (rig.timing)."""
    timing_error_s: float = 0.0
    """The largest misdating found (s)."""
    timing_fault: str | None = None
    """Why the data failed the timing checks (too many misdated samples: rig.timing), when they
    did: a check judging this calibration then gives RE-RUN, not PASS or FAIL."""

    def to_dict(self) -> dict[str, Any]:
        """The stored ``selection`` block (the counts stay top-level keys of the result)."""
        return {"steps": list(self.steps), "settle_s": self.settle_s,
                "telemetry": list(self.telemetry), "dut": self.dut, "reference": self.reference}  # fmt: skip

    @classmethod
    def from_result(cls, result: Mapping[str, Any]) -> SampleSelection | None:
        """The selection a stored result names; None for results recorded before they did."""
        sel = result.get("selection")
        if not isinstance(sel, dict):
            return None
        return cls(
            steps=tuple(str(s) for s in sel.get("steps", ())),
            settle_s=float(sel.get("settle_s", 0.0)),
            telemetry=tuple(str(c) for c in sel.get("telemetry", ())),
            dut=str(sel.get("dut", "dut")),
            reference=str(sel.get("reference", "reference")),
            unresolved=int(result.get("unresolved_field_samples", 0)),
            misdated=int(result.get("misdated_samples", 0)),
            timing_error_s=float(result.get("timing_error_s", 0.0)),
            timing_fault=str(result["timing_fault"]) if result.get("timing_fault") else None,
        )


@dataclass(frozen=True)
class LiveBlock:
    """Why a live (sequential) calibration stopped, and its 1-sigma then."""

    stopped: str
    updates: int
    elapsed_s: float
    noise_nt: float
    sigma_at_stop: dict[str, float]
    targets: dict[str, float]
    history_file: str = ""

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> LiveBlock:
        """From the stored ``live`` block."""
        return cls(str(d.get("stopped", "")), int(d.get("updates", 0)),
                   float(d.get("elapsed_s", 0.0)), float(d.get("noise_nt", float("nan"))),
                   {str(k): float(v) for k, v in dict(d.get("sigma_at_stop", {})).items()},
                   {str(k): float(v) for k, v in dict(d.get("targets", {})).items()},
                   str(d.get("history_file", "")))  # fmt: skip


CALIBRATION_VALUES = (
    "residual_rms_nt", "residual_mean_nt", "residual_max_nt", "samples", "iterations",
    "noise_nt", "noise_floor_nt", "noise_estimated_nt", "unresolved_field_samples",
    "misdated_samples", "timing_error_s", "springmann.*", "sigma.*", "crlb_ratio.*",
    "crlb_sigma.*", "crassidis.*", "chi2.*", "angular_uncertainty_deg.*", "correlations.*",
    "temperature.*", "mounting.*", "correction.*", "covariance.*", "combined_sigma.*",
    "uncertainty_budget.*",
)  # fmt: skip
"""The values a calibration result holds, as a check criterion names them (dotted paths,
``fnmatch`` patterns)."""


@dataclass(frozen=True)
class CalibrationRecord:
    """One stored calibration: model, method, correction, parameters with 1-sigma, residuals, the
    samples it used and, for a live one, why it stopped."""

    model: str
    method: str
    samples: int
    channels: tuple[str, ...]
    correction: dict[str, Any]
    """``h = matrix @ (m - offset_ut - sum_j k_j * u_j)``: matrix, offset_ut (uT), k_ut_per_unit."""
    springmann: dict[str, float]
    """a, b, c, x0_ut, y0_ut, z0_ut (uT), rho_deg, phi_deg, lambda_deg (deg)."""
    sigma: dict[str, Any]
    crlb_ratio: dict[str, Any]
    residual_rms_nt: float
    residual_mean_nt: float
    residual_max_nt: float
    chi2: dict[str, Any]
    angular_uncertainty_deg: dict[str, float]
    warnings: tuple[str, ...]
    selection: SampleSelection | None
    live: LiveBlock | None
    stored: dict[str, Any] = field(repr=False, compare=False)
    """The stored mapping as read: keys this record does not name pass through unchanged."""

    @staticmethod
    def is_one(value: Any) -> bool:
        """True when a stored result is a calibration (it has a correction and parameters)."""
        return (isinstance(value, dict) and isinstance(value.get("springmann"), dict)
                and isinstance(value.get("correction"), dict))  # fmt: skip

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CalibrationRecord:
        """Read a stored calibration result (any version the rig has written)."""
        live = d.get("live")
        return cls(
            model=str(d["model"]), method=str(d["method"]), samples=int(d["samples"]),
            channels=tuple(str(c) for c in d.get("channels", ())),
            correction=dict(d["correction"]), springmann=dict(d["springmann"]),
            sigma=dict(d.get("sigma", {})), crlb_ratio=dict(d.get("crlb_ratio", {})),
            residual_rms_nt=float(d["residual_rms_nt"]),
            residual_mean_nt=float(d.get("residual_mean_nt", float("nan"))),
            residual_max_nt=float(d.get("residual_max_nt", float("nan"))),
            chi2=dict(d.get("chi2", {})),
            angular_uncertainty_deg=dict(d.get("angular_uncertainty_deg", {})),
            warnings=tuple(str(w) for w in d.get("warnings", ())),
            selection=SampleSelection.from_result(d),
            live=LiveBlock.from_dict(live) if isinstance(live, dict) else None,
            stored=dict(d),
        )  # fmt: skip

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping (the same keys and values it was read from or built with)."""
        out = dict(self.stored)
        if self.selection is not None:
            sel = self.selection
            out["selection"] = sel.to_dict()
            out["unresolved_field_samples"] = sel.unresolved
            out["misdated_samples"] = sel.misdated
            out["timing_error_s"] = sel.timing_error_s
            if sel.timing_fault is not None:
                out["timing_fault"] = sel.timing_fault
        out["warnings"] = list(self.warnings)
        return out

    def sigma_of(self, key: str) -> float:
        """A Springmann parameter's 1-sigma (its unit), NaN when not stored."""
        return float(self.sigma.get("springmann", {}).get(key, float("nan")))

    def ratio_of(self, key: str) -> float:
        """A Springmann parameter's sigma / CRLB, NaN when not stored."""
        return float(self.crlb_ratio.get("springmann", {}).get(key, float("nan")))

    @property
    def k_ut_per_unit(self) -> dict[str, list[float]]:
        """Current-to-bias coefficients per load channel (uT/A)."""
        return dict(self.correction.get("k_ut_per_unit", {}))

    @property
    def mounting_deg(self) -> list[float] | None:
        """The DUT mounting rotation vector (deg) when the fit could observe it."""
        mounting = self.stored.get("mounting", {})
        if isinstance(mounting, dict) and mounting.get("observable"):
            return [float(v) for v in mounting["rotation_vector_deg"]]
        return None


def calibrations(results: Mapping[str, Any]) -> dict[str, CalibrationRecord]:
    """Every calibration among a run's stored results, by result name, in the order recorded."""
    return {n: CalibrationRecord.from_dict(v) for n, v in results.items()
            if CalibrationRecord.is_one(v)}  # fmt: skip


def latest_calibration(
    results: Mapping[str, Any], model: str | None = None
) -> tuple[str, CalibrationRecord] | None:
    """The run's latest calibration (the last one recorded; of ``model`` when given) with its
    result name; None before the first. The one lookup of 'the calibration of this run'."""
    found = {n: r for n, r in calibrations(results).items() if model in (None, r.model)}
    if not found:
        return None
    name = list(found)[-1]
    return name, found[name]
