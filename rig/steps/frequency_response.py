"""``frequency_response``: sine fields along each axis at a list of frequencies, and the DUT's
amplitude ratio and phase at each against the reference, the reference's own response removed
(:mod:`rig.characterization.frequency`).

Each axis holds ``bias_ut`` (so no coil changes polarity: a relay flip mid-sine would be a step,
not a sine), then for each frequency ``amplitude_ut`` of sine on top for ``settle_cycles`` (not
fitted) and ``cycles`` (fitted), as tracked set-points at ``rate_hz``. The DUT's readings are
corrected by the run's latest calibration and compared in its own axes (the reference field
turned by a vector calibration's mounting) when there is one. The reference's response comes from
its configuration (``response_tau_s``, ``response_integration_s``); the cage's own response
(the field made over the field asked) is measured at every frequency, and a frequency where it
fell under half power is beyond the cage's bandwidth: reported, not judged.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from rig.analysis import settled_samples, to_cage_frame
from rig.characterization.frequency import (
    ResponsePoint,
    first_order,
    phasor,
    relative_phasors,
    response_point,
)
from rig.errors import RigError
from rig.steps.base import Array, FieldStepKind, RunContext, StepExecution, load_commands
from rig.steps.sensor_axes import in_sensor_axes
from rig.steps.vocabulary import (
    MAX_FIELD_SETPOINTS_PER_STEP,
    Command,
    Param,
    ProcedureError,
    RigTiming,
    Step,
)

AXES = "xyz"


@dataclass(frozen=True)
class FrequencyResult:
    """Per axis, the response at each frequency; how the DUT and the reference were taken."""

    points: dict[str, tuple[ResponsePoint, ...]]
    frame: str
    reference_response: str

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping (criteria: ``amplitude_error_max``, ``phase_abs_max_deg`` over the
        frequencies within the cage's bandwidth; ``cage_bandwidth_hz``)."""
        judged = [p for ps in self.points.values() for p in ps if p.within_bandwidth]
        within = [p.f_hz for p in judged]
        return {
            "axes": {axis: [{"f_hz": p.f_hz, "amplitude": p.amplitude,
                             "amplitude_sigma": p.amplitude_sigma, "phase_deg": p.phase_deg,
                             "phase_sigma_deg": p.phase_sigma_deg,
                             "cage_amplitude": p.cage_amplitude, "cage_phase_deg": p.cage_phase_deg,
                             "within_bandwidth": p.within_bandwidth} for p in ps]
                     for axis, ps in self.points.items()},
            "amplitude_error_max": max((abs(p.amplitude - 1.0) for p in judged), default=None),
            "phase_abs_max_deg": max((abs(p.phase_deg) for p in judged), default=None),
            "cage_bandwidth_hz": max(within, default=None),
            "frame": self.frame, "reference_response": self.reference_response,
        }  # fmt: skip


class FrequencyResponse(FieldStepKind):
    name = "frequency_response"
    summary = "sine fields at each frequency: the DUT's amplitude ratio and phase (Bode plot)"
    result_values = ("axes", "amplitude_error_max", "phase_abs_max_deg", "cage_bandwidth_hz",
                     "frame", "reference_response")  # fmt: skip
    params: ClassVar[dict[str, Param]] = {
        "frequencies_hz": Param("list_float", [0.1, 0.2, 0.5, 1.0, 2.0]),
        "axes": Param("str", "xyz"),
        "amplitude_ut": Param("float", 10.0, 0.1, 1000.0),
        "bias_ut": Param("float", 30.0, 0.0, 1000.0),
        "cycles": Param("int", 4, 1, 10000),
        "min_s": Param("float", 8.0, 0.0, 86400.0),
        "settle_cycles": Param("int", 1, 0, 100),
        "settle_s": Param("float", 2.0, 0.0, 600.0),
        "rate_hz": Param("float", 25.0, 1.0, 200.0),
        "magnetometer": Param("str", "dut"),
    }

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        axes = params["axes"]
        if not axes or any(a not in AXES for a in axes) or len(set(axes)) != len(axes):
            raise ProcedureError(f"{where}: axes is some of x, y, z, each once (e.g. xyz)")
        if params["bias_ut"] <= params["amplitude_ut"]:
            raise ProcedureError(f"{where}: bias_ut must exceed amplitude_ut, so that no coil"
                                 " changes polarity during a sine")  # fmt: skip
        top = params["rate_hz"] / 5.0
        if not params["frequencies_hz"] or any(not 0 < f <= top for f in params["frequencies_hz"]):
            raise ProcedureError(f"{where}: frequencies_hz must be above 0 and at most rate_hz / 5"
                                 f" ({top:g} Hz: five set-points per cycle)")  # fmt: skip
        cycles = params["cycles"] + params["settle_cycles"]
        setpoints = (
            len(axes) * params["rate_hz"] * sum(cycles / f for f in params["frequencies_hz"])
        )
        if setpoints > MAX_FIELD_SETPOINTS_PER_STEP:
            raise ProcedureError(f"{where}: {setpoints:.0f} set-points, more than"
                                 f" {MAX_FIELD_SETPOINTS_PER_STEP} (MAX_FIELD_SETPOINTS_PER_STEP):"
                                 " fewer cycles at the lowest frequencies")  # fmt: skip

    def segments(self, step: Step) -> list[tuple[int, float, float, float]]:
        """(axis, frequency Hz, start s, seconds) of each sine, in the step's time: ``cycles``
        fitted, or as many as last ``min_s`` (a fast sine's few cycles are soon over)."""
        p, t, out = step.params, 0.0, []
        for axis in p["axes"]:
            t += float(p["settle_s"])
            for f in p["frequencies_hz"]:
                fitted = max(int(p["cycles"]), math.ceil(float(p["min_s"]) * float(f) - 1e-9))
                length = (fitted + int(p["settle_cycles"])) / float(f)
                out.append((AXES.index(axis), float(f), t, length))
                t += length
        return out

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        *_, start, length = self.segments(step)[-1]
        return start + length

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        """Each axis's bias as it starts (the sines are the step's own tracked set-points)."""
        p, out = step.params, []
        starts: dict[int, float] = {}
        for axis, _f, start, _length in self.segments(step):
            starts.setdefault(axis, start - float(p["settle_s"]))
        for axis, t in starts.items():
            v = np.zeros(3)
            v[axis] = float(p["bias_ut"])
            out.append((t, v))
        return out

    def compile(self, step: Step, base: Path, timing: RigTiming) -> tuple[list[Command], float]:
        p = step.params
        duration = self.duration_s(step, timing)
        cmds = [
            Command(t, "field", self.field_payload(step, f)) for t, f in self.fields(step, timing)
        ]
        rate, amp, bias = float(p["rate_hz"]), float(p["amplitude_ut"]), float(p["bias_ut"])
        for axis, f, start, length in self.segments(step):
            for k in range(1, round(length * rate) + 1):
                v = np.zeros(3)
                v[axis] = bias + amp * math.sin(2.0 * math.pi * f * k / rate)
                cmds.append(Command(start + k / rate, "field",
                                    {"field_ut": [float(x) for x in v], "trim": False,
                                     "track": True, "segment": [axis, f]}))  # fmt: skip
        cmds += load_commands(step, duration, base)
        cmds.append(Command(duration, "end", {}))
        return cmds, duration

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return MeasureFrequencyResponse(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        if not isinstance(result, Mapping) or "axes" not in result:
            return []
        lines = [
            f"Frequency response '{name}' ({result['frame']} axes; {result['reference_response']}):"
        ]
        for axis, points in result["axes"].items():
            cells = [f"{p['f_hz']:g} Hz {p['amplitude']:.4f} +- {p['amplitude_sigma']:.4f},"
                     f" {p['phase_deg']:+.2f} +- {p['phase_sigma_deg']:.2f} deg"
                     + ("" if p["within_bandwidth"] else " (beyond the cage's bandwidth)")
                     for p in points]  # fmt: skip
            lines.append(f"  {axis}: " + "; ".join(cells))
        return lines

    def figures(self, reader: Any, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        if not isinstance(result, Mapping) or "axes" not in result:
            return []
        fig, (top, bottom) = plt.subplots(2, 1, figsize=(7.0, 5.0), sharex=True)
        for axis, points in result["axes"].items():
            f = [p["f_hz"] for p in points]
            for ax, value, sigma, cage in ((top, "amplitude", "amplitude_sigma", "cage_amplitude"),
                                           (bottom, "phase_deg", "phase_sigma_deg", "cage_phase_deg")):  # fmt: skip
                ax.errorbar(f, [p[value] for p in points], yerr=[p[sigma] for p in points],
                            fmt="o-", ms=3, label=axis)  # fmt: skip
                ax.plot(f, [p[cage] for p in points], ":", color="0.5", lw=0.8)
        top.set_xscale("log")
        top.set_ylabel("amplitude ratio")
        bottom.set_ylabel("phase (deg)")
        bottom.set_xlabel("frequency (Hz); dotted: the cage's own")
        for ax in (top, bottom):
            ax.grid(alpha=0.3, which="both")
        top.legend(fontsize=7)
        return [(f"Frequency response ('{name}'): Bode plot, 1-sigma", fig)]


class MeasureFrequencyResponse(StepExecution):
    """After the sines: per axis and frequency, the DUT, the reference and the set-points fitted."""

    def finish(self, t_start: float, t_end: float) -> None:
        p = self.step.params
        mags = self.ctx.proc.magnetometers
        dut, ref = mags.get(p["magnetometer"], p["magnetometer"]), mags.get("reference")
        if ref is None or ref not in self.ctx.samplers:
            raise RigError(f"frequency_response '{self.step.name}' needs a sampled 'reference'")
        known = self.ctx.cfg.devices if self.ctx.cfg is not None else {}
        ref_cfg = known.get(ref)
        tau = float(ref_cfg.get("response_tau_s") or 0.0) if ref_cfg is not None else 0.0
        window = float(ref_cfg.get("response_integration_s") or 0.0) if ref_cfg is not None else 0.0
        reader = self.ctx.open_reader()
        try:
            rows = settled_samples(reader, dut, (t_start, t_end), 0.0)
            refs = settled_samples(reader, ref, (t_start, t_end), 0.0)
            sent = [(t, pl) for t, s, k, pl in reader.commands()
                    if s == self.step.index and k == "field" and "segment" in pl]  # fmt: skip
        finally:
            reader.close()
        m, h, frame = self._frames(rows[:, 1:], to_cage_frame(refs[:, 1:], self.ctx.correction))
        points: dict[str, list[ResponsePoint]] = {}
        for axis, f, _start, _length in KIND.segments(self.step):
            cmds = [(t, pl["field_ut"][axis]) for t, pl in sent if pl["segment"] == [axis, f]]
            skip = round(int(p["settle_cycles"]) / f * float(p["rate_hz"]))
            if len(cmds) <= skip + 4:
                raise RigError(f"frequency_response '{self.step.name}': the {f:g} Hz sine on"
                               f" {AXES[axis]} was not sent (the step ended early)")  # fmt: skip
            c = np.asarray(cmds[skip:], float)
            span = (c[0, 0], c[-1, 0] + 1.0 / float(p["rate_hz"]))
            kd = (rows[:, 0] >= span[0]) & (rows[:, 0] < span[1])
            kr = (refs[:, 0] >= span[0]) & (refs[:, 0] < span[1])
            rate = float(p["rate_hz"])
            dut_p, ref_p = relative_phasors((rows[kd, 0], m[kd, axis]), (refs[kr, 0], h[kr, axis]), f,
                                            _staircase(rows[kd, 0], rate, f),
                                            _staircase(refs[kr, 0], rate, f))  # fmt: skip
            point = response_point(f, dut_p, ref_p, phasor(c[:, 0], c[:, 1], f),
                                   first_order(tau, window, f))  # fmt: skip
            points.setdefault(AXES[axis], []).append(point)
        note = (f"the reference's response (tau {tau:g} s, window {window:g} s) removed"
                if tau or window else "the reference taken as ideal (no response_tau_s given)")  # fmt: skip
        result = FrequencyResult({k: tuple(v) for k, v in points.items()}, frame, note)
        self.ctx.record_result(self.step.name, result.to_dict())

    def _frames(self, m: Array, h: Array) -> tuple[Array, Array, str]:
        """The DUT's readings and the reference field in the DUT's axes (a vector calibration's
        correction and mounting), else both as they are (the cage's axes, raw readings)."""
        axes = in_sensor_axes(self.ctx.results, h, m)
        if axes.calibration is None:
            return m, h, "cage (no vector calibration: the amplitude holds the DUT's scale error)"
        return axes.readings_ut, axes.field_ut, "sensor"


def _staircase(t_s: Array, rate_hz: float, f_hz: float) -> tuple[float, ...]:
    """The set-points' staircase lines (the set-point rate and its double, plus and minus the
    sine's frequency) as a device sampling at times ``t_s`` sees them: aliased into its band,
    and left out where one lands on the sine itself or on zero (it cannot be told from them)."""
    if len(t_s) < 2:
        return ()
    fs = 1.0 / float(np.median(np.diff(t_s)))
    resolution = 1.5 / float(t_s[-1] - t_s[0])
    out: list[float] = []
    for line in (rate_hz - f_hz, rate_hz + f_hz, 2 * rate_hz - f_hz, 2 * rate_hz + f_hz):
        seen = abs(line - round(line / fs) * fs)
        apart = all(abs(seen - g) > resolution for g in (0.0, f_hz, *out))
        if apart and seen < 0.5 * fs - resolution:
            out.append(seen)
    return tuple(out)


KIND = FrequencyResponse()
