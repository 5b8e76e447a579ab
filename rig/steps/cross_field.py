"""``cross_field``: sweep each axis while a field across it is held at -B, 0 and +B, and fit how
much that field changes the axis's scale (ppm per uT; :mod:`rig.characterization.cross_field`).

With a vector calibration of the DUT earlier in the run the fit is in the sensor's own axes (the
reference field turned by the calibration's mounting rotation, the readings corrected by it):
what a datasheet means by a cross-field coefficient. Without one it is in the cage's axes and the
result says that a mounting rotation of a few degrees mixes about that fraction of the other
transverse coefficient in.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from rig.analysis import interpolated_field, settled_samples
from rig.characterization.cross_field import CrossField, fit_cross_field
from rig.errors import RigError
from rig.steps.base import Array, FieldStepKind, RunContext, SettledNeed, StepExecution
from rig.steps.sensor_axes import in_sensor_axes
from rig.steps.vocabulary import ProcedureError, RigTiming, Step, StepParam

AXES = "xyz"


@dataclass(frozen=True)
class CrossFieldResult:
    """Every axis's coefficient towards each other axis (ppm of scale per uT) with 1-sigma, the
    axes they are in (``sensor`` or ``cage``) and the samples."""

    fits: tuple[CrossField, ...]
    frame: str
    frame_note: str
    transverse_ut: float

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping: 3x3 tables (rows the measured axis, the diagonal null) and
        ``max_abs_ppm_per_ut`` for criteria."""
        table: list[list[float | None]] = [[None] * 3 for _ in range(3)]
        sigma: list[list[float | None]] = [[None] * 3 for _ in range(3)]
        for f in self.fits:
            table[f.axis][f.transverse] = f.ppm_per_ut
            sigma[f.axis][f.transverse] = f.sigma_ppm_per_ut
        return {
            "cross_field_ppm_per_ut": table, "sigma_ppm_per_ut": sigma,
            "max_abs_ppm_per_ut": max(abs(f.ppm_per_ut) for f in self.fits),
            "residual_nt": [next(f.residual_nt for f in self.fits if f.axis == i) for i in range(3)],
            "samples": self.fits[0].samples, "frame": self.frame, "frame_note": self.frame_note,
            "transverse_ut": self.transverse_ut,
        }  # fmt: skip


def pairs() -> list[tuple[int, int]]:
    """(measured axis, transverse axis) in the order the step sweeps them."""
    return [(i, j) for i in range(3) for j in range(3) if i != j]


class CrossFieldKind(FieldStepKind):
    name = "cross_field"
    summary = "each axis's scale with a field across it: the cross-field coefficients (ppm/uT)"
    result_values = ("cross_field_ppm_per_ut", "sigma_ppm_per_ut", "max_abs_ppm_per_ut",
                     "residual_nt", "samples", "frame", "transverse_ut")  # fmt: skip
    params: ClassVar[dict[str, StepParam]] = {
        "transverse_ut": StepParam("float", 40.0, 1.0, 1000.0),
        "levels_ut": StepParam("list_float", [-45.0, -30.0, -15.0, 15.0, 30.0, 45.0]),
        "dwell_s": StepParam("float", 1.0, 0.1, 600.0),
        "settle_s": StepParam("float", 0.3, 0.0, 60.0),
        "magnetometer": StepParam("str", "dut"),
    }

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        levels = params["levels_ut"]
        if len({round(v, 9) for v in levels}) < 3 or any(abs(v) > 1000.0 for v in levels):
            raise ProcedureError(f"{where}: levels_ut needs at least 3 different levels within"
                                 " +-1000 uT (the scale and its change are fitted on them)")  # fmt: skip
        if params["settle_s"] >= params["dwell_s"]:
            raise ProcedureError(f"{where}: settle_s must be shorter than dwell_s")

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        p = step.params
        out: list[tuple[float, Array]] = []
        for i, j in pairs():
            for across in (-p["transverse_ut"], 0.0, p["transverse_ut"]):
                for level in p["levels_ut"]:
                    v = np.zeros(3)
                    v[i], v[j] = level, across
                    out.append((len(out) * p["dwell_s"], v))
        return out

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return len(self.fields(step, timing)) * float(step.params["dwell_s"])

    def settled_need(self, step: Step, magnetometers: Mapping[str, str]) -> SettledNeed:
        """A settled sample of the DUT and the reference at every field (54 or more in all)."""
        dut = magnetometers.get(step.params["magnetometer"], step.params["magnetometer"])
        devices = (dut, magnetometers["reference"]) if "reference" in magnetometers else (dut,)
        return SettledNeed(devices, 1, float(step.params["settle_s"]))

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return MeasureCrossField(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        if not isinstance(result, Mapping) or "cross_field_ppm_per_ut" not in result:
            return []
        table, sigma = result["cross_field_ppm_per_ut"], result["sigma_ppm_per_ut"]
        cells = [f"{AXES[i]} across {AXES[j]} {table[i][j]:+.1f} +- {sigma[i][j]:.1f}"
                 for i, j in pairs()]  # fmt: skip
        return [f"Cross-field '{name}' (ppm of scale per uT, {result['frame']} axes):"
                f" {'; '.join(cells)}"]  # fmt: skip


class MeasureCrossField(StepExecution):
    """After the sweeps: the DUT against the reference, in the sensor's axes when calibrated."""

    def finish(self, t_start: float, t_end: float) -> None:
        p = self.step.params
        mags = self.ctx.proc.magnetometers
        dut, ref = mags.get(p["magnetometer"], p["magnetometer"]), mags.get("reference")
        if ref is None:
            raise RigError(f"cross_field '{self.step.name}' needs a 'reference' magnetometer")
        reader = self.ctx.open_reader()
        try:
            rows = settled_samples(reader, dut, (t_start, t_end), float(p["settle_s"]))
            refs = settled_samples(reader, ref, (t_start, t_end), float(p["settle_s"]))
        finally:
            reader.close()
        if len(rows) < 30 or len(refs) < 2:
            raise RigError(f"cross_field '{self.step.name}': too few settled samples"
                           f" ({len(rows)} of '{dut}'): lengthen dwell_s")  # fmt: skip
        t, m = rows[:, 0], rows[:, 1:]
        h = interpolated_field(refs, t, self.ctx.correction)
        h_axes, m_axes, frame, note = self._axes(h, m)
        fits = tuple(f for i in range(3) for f in fit_cross_field(h_axes, m_axes, i))
        result = CrossFieldResult(fits, frame, note, float(p["transverse_ut"]))
        self.ctx.record_result(self.step.name, result.to_dict())

    def _axes(self, h: Array, m: Array) -> tuple[Array, Array, str, str]:
        """The field and readings in the sensor's axes (a vector calibration of this run), else
        as they are (the cage's axes, the raw readings)."""
        axes = in_sensor_axes(self.ctx.results, h, m)
        if axes.calibration is None or axes.mounting_deg is None:
            return h, m, "cage", ("the cage's axes (no vector calibration earlier in the run): a"
                                  " mounting rotation of a few degrees mixes that fraction of"
                                  " the other transverse coefficient in")  # fmt: skip
        return (axes.field_ut, axes.readings_ut, "sensor",
                f"the sensor's axes (calibration '{axes.calibration}', mounting"
                f" {', '.join(f'{v:.2f}' for v in axes.mounting_deg)} deg)")  # fmt: skip


KIND = CrossFieldKind()
