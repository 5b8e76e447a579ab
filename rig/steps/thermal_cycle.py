"""``thermal_cycle``: hold the null field while the step's load profiles (a heater on the DUT's
mount) warm and cool the DUT, and fit its offset against the recorded temperature on the warming
and the cooling branch: the thermal hysteresis (warming less cooling) and the temperature
coefficient, each with a sigma (:mod:`rig.characterization.thermal`).

The offset is the DUT (corrected by the run's latest calibration) less the reference (inside the
coils; ``none``: nothing subtracted, and the result says the lab field is in it). The heater's
current is a term of the fit (a pad's current can bias the sensor, and it is on while warming):
hold one temperature on both branches at the same current (warm to it, go hotter, come back down
to it) or the hysteresis cannot be told from that bias, and the step says so. The offset's own
wander is counted in the sigmas; cycling more than once lets its drift be told from hysteresis.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from rig.analysis import hold_values, thermometer_at
from rig.characterization.thermal import ThermalFit, fit_thermal
from rig.errors import RigError
from rig.steps.at_rest import offsets_at_rest
from rig.steps.base import NullHoldKind, RunContext, StepExecution
from rig.steps.vocabulary import ProcedureError, Step, StepParam

MIN_SAMPLES = 100


@dataclass(frozen=True)
class ThermalCycleResult:
    """The fit and how it was made."""

    fit: ThermalFit
    thermometer: str
    temperature_range_c: tuple[float, float]
    samples: int
    calibrated: bool
    reference_note: str

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping (criteria: ``hysteresis_abs_max_nt``, ``significance_sigma``,
        ``tempco_abs_max_nt_per_k``)."""
        f = self.fit
        return {
            "hysteresis_nt": list(f.hysteresis_nt), "hysteresis_sigma_nt": list(f.hysteresis_sigma_nt),
            "hysteresis_abs_max_nt": max(abs(v) for v in f.hysteresis_nt),
            "significance_sigma": f.significance_sigma, "detected": f.detected,
            "tempco_nt_per_k": list(f.tempco_nt_per_k),
            "tempco_sigma_nt_per_k": list(f.tempco_sigma_nt_per_k),
            "tempco_abs_max_nt_per_k": max(abs(v) for v in f.tempco_nt_per_k),
            "drift_nt_per_h": list(f.drift_nt_per_h), "drift_sigma_nt_per_h": list(f.drift_sigma_nt_per_h),
            "reference_c": f.reference_c,
            "bins": {"temperature_c": list(f.bin_temperature_c), "branch": list(f.bin_branch),
                     "offset_nt": [list(r) for r in f.bin_offset_nt], "samples": list(f.bin_samples)},
            "thermometer": self.thermometer, "temperature_range_c": list(self.temperature_range_c),
            "samples": self.samples, "calibrated": self.calibrated,
            "reference_note": self.reference_note,
        }  # fmt: skip


class ThermalCycle(NullHoldKind):
    name = "thermal_cycle"
    summary = "null field while a heater warms and cools the DUT: thermal hysteresis and tempco"
    result_values = ("hysteresis_nt", "hysteresis_sigma_nt", "hysteresis_abs_max_nt",
                     "significance_sigma", "detected", "tempco_nt_per_k", "tempco_sigma_nt_per_k",
                     "tempco_abs_max_nt_per_k", "drift_nt_per_h", "reference_c",
                     "temperature_range_c", "samples", "calibrated")  # fmt: skip
    params: ClassVar[dict[str, StepParam]] = {
        "hold_s": StepParam("float", 3600.0, 10.0, 7 * 86400.0),
        "thermometer": StepParam("str", ""),
        "reference": StepParam("str", "reference", choices=("reference", "none")),
        "trim": StepParam("str", "yes", choices=("yes", "no")),
        "settle_s": StepParam("float", 2.0, 0.0, 600.0),
        "reversal_k": StepParam("float", 1.0, 0.01, 100.0),
        "bin_k": StepParam("float", 0.5, 0.01, 100.0),
        "bin_s": StepParam("float", 60.0, 1.0, 86400.0),
        "magnetometer": StepParam("str", "dut"),
    }

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        if not params["thermometer"]:
            raise ProcedureError(f"{where}: name the DUT's thermometer (thermometer: dut_temp)")

    def check_against(self, step: Step, earlier: Sequence[Step]) -> None:
        if not step.loads:
            raise ProcedureError(f"{step.where.path}:{step.where.line}: step {step.index + 1}"
                                 f" ({self.name}): give the heater's profile under loads: (warm to"
                                 " a temperature, go hotter, come back down to it)")  # fmt: skip

    def thermometers(self, step: Step) -> tuple[str, ...]:
        return (str(step.params["thermometer"]),)

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return MeasureThermalCycle(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        if not isinstance(result, Mapping) or "hysteresis_nt" not in result:
            return []
        hyst = ", ".join(f"{v:+.2f} +- {s:.2f}" for v, s in
                         zip(result["hysteresis_nt"], result["hysteresis_sigma_nt"], strict=True))  # fmt: skip
        tc = ", ".join(f"{v:+.2f}" for v in result["tempco_nt_per_k"])
        lo, hi = result["temperature_range_c"]
        seen = "detected" if result["detected"] else "not detected"
        return [f"Thermal cycle '{name}' ({lo:.1f}-{hi:.1f} C on '{result['thermometer']}'):"
                f" hysteresis (warming less cooling) {hyst} nT (x, y, z),"
                f" {result['significance_sigma']:.1f} sigma: {seen}; offset tempco {tc} nT/K"]  # fmt: skip

    def figures(self, reader: Any, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        if not isinstance(result, Mapping) or "bins" not in result:
            return []
        b = result["bins"]
        temp, branch = np.asarray(b["temperature_c"]), np.asarray(b["branch"])
        offset = np.asarray(b["offset_nt"])
        fig, axes = plt.subplots(1, 3, figsize=(9.0, 3.2), sharex=True)
        for i, ax in enumerate(axes):
            for sign, colour, label in ((1, "tab:red", "warming"), (-1, "tab:blue", "cooling")):
                k = branch == sign
                ax.plot(temp[k], offset[k, i], ".", ms=3, color=colour, label=label)
            ax.set_title("xyz"[i], fontsize=9)
            ax.set_xlabel("temperature (C)")
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("offset (nT)")
        axes[0].legend(fontsize=7)
        return [(f"Thermal cycle ('{name}'): offset on warming and cooling", fig)]


class MeasureThermalCycle(StepExecution):
    """After the hold: the DUT's offset against the thermometer, fitted per branch."""

    def finish(self, t_start: float, t_end: float) -> None:
        p = self.step.params
        mags = self.ctx.proc.magnetometers
        dut = mags.get(p["magnetometer"], p["magnetometer"])
        ref = mags.get("reference") if p["reference"] == "reference" else None
        if p["reference"] == "reference" and (ref is None or ref not in self.ctx.samplers):
            raise RigError(f"thermal_cycle '{self.step.name}': no 'reference' magnetometer is"
                           " sampled; use reference: none (the lab field then stays in)")  # fmt: skip
        (rest,) = offsets_at_rest(self.ctx, dut, ref, [(t_start, t_end)], float(p["settle_s"]))
        t, offsets = rest.t_s, rest.offsets_nt
        if len(t) < MIN_SAMPLES:
            raise RigError(f"thermal_cycle '{self.step.name}': {len(t)} settled samples (at least"
                           f" {MIN_SAMPLES}): lengthen hold_s, or shorten settle_s"
                           f" ({float(p['settle_s']):g} s) below the loads' dwell")  # fmt: skip
        reader = self.ctx.open_reader()
        try:
            temperature, known = thermometer_at(reader, str(p["thermometer"]), t)
            currents = np.column_stack([hold_values(reader, ch, t) for ch in self.step.loads])
        finally:
            reader.close()
        t, offsets, temperature, currents = (
            t[known],
            offsets[known],
            temperature[known],
            currents[known],
        )
        if len(t) < MIN_SAMPLES:
            raise RigError(f"thermal_cycle '{self.step.name}': {len(t)} settled samples with a"
                           " temperature: lengthen hold_s or check the thermometer")  # fmt: skip
        try:
            fit = fit_thermal(t, temperature, offsets, currents, float(p["reversal_k"]),
                              float(p["bin_k"]), float(p["bin_s"]))  # fmt: skip
        except ValueError as exc:
            raise RigError(f"thermal_cycle '{self.step.name}': {exc}") from None
        note = (f"the reference '{ref}' subtracted" if ref is not None
                else "nothing subtracted: the lab field's changes are in it")  # fmt: skip
        result = ThermalCycleResult(fit, str(p["thermometer"]),
                                    (float(temperature.min()), float(temperature.max())), len(t),
                                    rest.calibrated, note)  # fmt: skip
        self.ctx.record_result(self.step.name, result.to_dict())


KIND = ThermalCycle()
