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
from typing import Any, ClassVar

import numpy as np

from rig.analysis import settled_samples, to_cage_frame
from rig.characterization.frequency import (
    ResponsePoint,
    corner_hz,
    phasor,
    relative_phasors,
    response_point,
    with_systematics,
)
from rig.characterization.staircase_images import image_spread
from rig.steps.base import (
    Array,
    RunContext,
    StepExecution,
)
from rig.steps.sensor_axes import in_sensor_axes
from rig.steps.sine_fields import (
    AXES,
    SINE_PARAMS,
    Segment,
    SineStepKind,
    bode_figure,
    commanded,
    reference_response,
    segments,
    sent_sines,
    slipped,
    span_of,
    staircase,
)
from rig.steps.vocabulary import Step, StepParam

Fitted = tuple[Array, tuple[float, ...]]
"""A device's sample times (s) within a sine and the staircase lines fitted beside it (Hz)."""


@dataclass(frozen=True)
class FrequencyResult:
    """Per axis, the response at each frequency; how the DUT and the reference were taken; the
    points whose sine was not made on time (``slips``: per axis and point, why, or None)."""

    points: dict[str, tuple[ResponsePoint, ...]]
    frame: str
    reference_response: str
    slips: dict[str, tuple[str | None, ...]]

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping (criteria: ``amplitude_error_max``, ``phase_abs_max_deg`` over the
        frequencies within the cage's bandwidth whose sines were made on time;
        ``cage_bandwidth_hz``); ``timing_fault`` when a sine was not (a check judging the result
        then asks for a re-run)."""
        axes: dict[str, list[dict[str, Any]]] = {}
        on_time: list[ResponsePoint] = []
        for axis, ps in self.points.items():
            axes[axis] = []
            for p, slip in zip(ps, self.slips[axis], strict=True):
                axes[axis].append(_point_dict(p, slip))
                if slip is None:
                    on_time.append(p)
        judged = [p for p in on_time if p.within_bandwidth]
        within = [p.f_hz for p in judged]
        slips = [why for whys in self.slips.values() for why in whys if why is not None]
        total = sum(len(whys) for whys in self.slips.values())
        out = {
            "axes": axes,
            "amplitude_error_max": max((abs(p.amplitude - 1.0) for p in judged), default=None),
            "phase_abs_max_deg": max((abs(p.phase_deg) for p in judged), default=None),
            "cage_bandwidth_hz": max(within, default=None),
            "frame": self.frame, "reference_response": self.reference_response,
        }  # fmt: skip
        if slips:
            out["timing_fault"] = (
                f"{len(slips)} of {total} sines not judged, made or read off time on a busy"
                f" computer ({'; '.join(slips[:3])}{'; ...' if len(slips) > 3 else ''}): measure"
                " again on a quieter computer"
            )
        return out


def _point_dict(p: ResponsePoint, slip: str | None) -> dict[str, Any]:
    """One stored point; ``not_judged`` says why when its sine was not made on time (its cage
    values, from a stretched sine, mean nothing then)."""
    d = {"f_hz": p.f_hz, "amplitude": p.amplitude, "amplitude_sigma": p.amplitude_sigma,
         "phase_deg": p.phase_deg, "phase_sigma_deg": p.phase_sigma_deg,
         "cage_amplitude": p.cage_amplitude, "cage_phase_deg": p.cage_phase_deg,
         "within_bandwidth": p.within_bandwidth}  # fmt: skip
    return d if slip is None else d | {"not_judged": slip}


class FrequencyResponse(SineStepKind):
    name = "frequency_response"
    summary = "sine fields at each frequency: the DUT's amplitude ratio and phase (Bode plot)"
    result_values = ("axes", "amplitude_error_max", "phase_abs_max_deg", "cage_bandwidth_hz",
                     "frame", "reference_response")  # fmt: skip
    params: ClassVar[dict[str, StepParam]] = {
        **SINE_PARAMS,
        "magnetometer": StepParam("str", "dut"),
    }
    cage_metrology_used = "cage_response"

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
                     + (f" (not judged: {p['not_judged']})" if p.get("not_judged")
                        else "" if p["within_bandwidth"] else " (beyond the cage's bandwidth)")
                     for p in points]  # fmt: skip
            lines.append(f"  {axis}: " + "; ".join(cells))
        return lines

    def figures(self, reader: Any, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        if not isinstance(result, Mapping) or "axes" not in result:
            return []
        fig = bode_figure(result, plt, "amplitude ratio", "the cage's own",
                          ("cage_amplitude", "cage_phase_deg"))  # fmt: skip
        return [(f"Frequency response ('{name}'): Bode plot, 1-sigma", fig)]


class MeasureFrequencyResponse(StepExecution):
    """After the sines: per axis and frequency, the DUT, the reference and the set-points fitted."""

    def finish(self, t_start: float, t_end: float) -> None:
        p = self.step.params
        dut = self.ctx.proc.magnetometers.get(p["magnetometer"], p["magnetometer"])
        ref = reference_response(self.ctx, self.step)
        reader = self.ctx.open_reader()
        try:
            rows = settled_samples(reader, dut, (t_start, t_end), 0.0)
            refs = settled_samples(reader, ref.name, (t_start, t_end), 0.0)
            dates = [_dates(reader, name) for name in (dut, ref.name)]
            sent = sent_sines(reader, self.step)
        finally:
            reader.close()
        m, h, frame = self._frames(rows[:, 1:], to_cage_frame(refs[:, 1:], self.ctx.correction))
        rate = float(p["rate_hz"])
        measured: list[tuple[Segment, ResponsePoint, tuple[float, float], list[Fitted]]] = []
        slips: dict[str, list[str | None]] = {}
        for s in segments(p):
            c = commanded(self.step, sent, s)
            slips.setdefault(AXES[s.axis], []).append(slipped(self.step, sent, s))
            span = span_of(c, rate)
            kd = (rows[:, 0] >= span[0]) & (rows[:, 0] < span[1])
            kr = (refs[:, 0] >= span[0]) & (refs[:, 0] < span[1])
            fits = [(t, staircase(t, rate, s.f_hz)) for t in (rows[kd, 0], refs[kr, 0])]
            dut_p, ref_p = relative_phasors((rows[kd, 0], m[kd, s.axis]),
                                            (refs[kr, 0], h[kr, s.axis]), s.f_hz,
                                            fits[0][1], fits[1][1])  # fmt: skip
            point = response_point(s.f_hz, dut_p, ref_p, phasor(c[:, 0], c[:, 1], s.f_hz),
                                   ref.at(s.f_hz))  # fmt: skip
            measured.append((s, point, span, fits))
        corners: dict[int, float] = {}  # per axis, the cage's fall from its lowest point
        for s, point, *_ in measured:
            corner = corner_hz(point.f_hz, point.cage_amplitude)
            corners[s.axis] = min(corners.get(s.axis, math.inf), corner)
        points: dict[str, list[ResponsePoint]] = {}
        for s, point, span, fits in measured:
            image = image_spread(s.f_hz, rate, fits, corners[s.axis])
            timing = math.hypot(*(_date_sigma_s(d, span) for d in dates))
            points.setdefault(AXES[s.axis], []).append(
                with_systematics(point, (image.amplitude, image.phase_rad), timing)
            )
            at = len(points[AXES[s.axis]]) - 1
            if slips[AXES[s.axis]][at] is None and timing * s.f_hz > MAX_DATE_CYCLES:
                slips[AXES[s.axis]][at] = (f"{AXES[s.axis]} {s.f_hz:g} Hz: its samples' dates known"
                                           f" to {1e3 * timing:.3g} ms only")  # fmt: skip
        result = FrequencyResult({k: tuple(v) for k, v in points.items()}, frame, ref.note(),
                                 {k: tuple(v) for k, v in slips.items()})  # fmt: skip
        self.ctx.record_result(self.step.name, result.to_dict())

    def _frames(self, m: Array, h: Array) -> tuple[Array, Array, str]:
        """The DUT's readings and the reference field in the DUT's axes (a vector calibration's
        correction and mounting), else both as they are (the cage's axes, raw readings)."""
        axes = in_sensor_axes(self.ctx.results, h, m)
        if axes.calibration is None:
            return m, h, "cage (no vector calibration: the amplitude holds the DUT's scale error)"
        return axes.readings_ut, axes.field_ut, "sensor"


MAX_DATE_CYCLES = 0.02
"""A point whose samples' dates are known no better than this fraction of its period (1-sigma:
7 degrees of phase) is not judged: a stream that stalled or restarted within its sine."""


def _dates(reader: Any, device: str) -> Array:
    """Rows (date s, its uncertainty s: a half-width, NaN when not recorded) of a device."""
    rows = reader.dated_samples(device)
    return np.asarray([(r[0], r[4]) for r in rows], float).reshape(-1, 2)


def _date_sigma_s(dates: Array, span: tuple[float, float]) -> float:
    """The 1-sigma (s) of a device's dates within ``span``, common to the span (a date comes from
    the stream's envelope, shared by its neighbours): the median half-width over the square root
    of 3 (uniform within it); 0 when the run did not record it."""
    inside = dates[(dates[:, 0] >= span[0]) & (dates[:, 0] < span[1]), 1]
    inside = inside[np.isfinite(inside)]
    return float(np.median(inside)) / math.sqrt(3.0) if len(inside) else 0.0


KIND = FrequencyResponse()
