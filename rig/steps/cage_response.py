"""``cage_response``: the cage's own bandwidth. Sine fields along each axis at a list of
frequencies (the set-points, the supplies and the coils' L/R together), read by the reference with
its configured response removed; per axis the amplitude and phase of the field made over the field
asked, and the frequency where it falls to half power. Kept in the cage record (``metrology``):
``rig check`` and every later run refuse a ``frequency_response`` above it."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

from rig.analysis import settled_samples, to_cage_frame
from rig.characterization.frequency import (
    ResponsePoint,
    cage_point,
    half_power_hz,
    phasor,
)
from rig.steps.base import (
    CageAbilities,
    RunContext,
    StepExecution,
    record_cage_metrology,
)
from rig.steps.sine_fields import (
    AXES,
    SINE_PARAMS,
    SineStepKind,
    beyond_the_cage,
    bode_figure,
    commanded,
    reference_phasor,
    reference_response,
    segments,
    sent_sines,
    slipped,
    span_of,
    within,
)
from rig.steps.vocabulary import Step, StepParam


class CageResponse(SineStepKind):
    name = "cage_response"
    summary = "sine fields at each frequency: the cage's own amplitude and phase, its bandwidth"
    result_values = ("axes", "bandwidth_hz", "bandwidth_hz.*", "limit_hz", "limit_hz.*",
                     "poorly_measured_hz", "measured_to_hz", "reference_response")  # fmt: skip
    params: ClassVar[dict[str, StepParam]] = {
        **SINE_PARAMS,
        "frequencies_hz": StepParam("list_float", [0.5, 1.0, 2.0, 3.0, 4.0, 5.0]),
        "cycles": StepParam("int", 3, 1, 10000),
        "min_s": StepParam("float", 3.0, 0.0, 86400.0),
    }

    def beyond_cage(self, step: Step, cage: CageAbilities) -> list[str]:
        """The slew limit and the polarity relays, never the bandwidth: this step measures it."""
        return beyond_the_cage(step, CageAbilities(cage.k_ut_per_a, cage.max_slew_a_per_s,
                                                   b0_ut=cage.b0_ut,
                                                   polarity_relays=cage.polarity_relays,
                                                   coil_tau_s=cage.coil_tau_s))  # fmt: skip

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return MeasureCageResponse(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        if not isinstance(result, Mapping) or "axes" not in result:
            return []
        lines = [f"Cage response '{name}' ({result['reference_response']}):"]
        for axis, points in result["axes"].items():
            found, limit = result["bandwidth_hz"].get(axis), result["limit_hz"].get(axis)
            edge = (f"half power at {found:.3g} Hz" if found is not None
                    else f"above half power up to {limit:g} Hz" if limit is not None
                    else "no frequency measured well enough")  # fmt: skip
            cells = [f"{p['f_hz']:g} Hz {p['amplitude']:.3f} {p['phase_deg']:+.1f} deg"
                     for p in points]  # fmt: skip
            lines.append(f"  {axis}: {edge}; " + "; ".join(cells))
        return lines

    def figures(self, reader: Any, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        if not isinstance(result, Mapping) or "axes" not in result:
            return []
        fig = bode_figure(result, plt, "field made / asked", "half power")
        fig.axes[0].axhline(2**-0.5, color="0.5", ls=":", lw=0.8)
        return [(f"Cage response ('{name}'): the field made over the field asked, 1-sigma", fig)]


class MeasureCageResponse(StepExecution):
    """After the sines: per axis and frequency, the reference and the set-points fitted; the
    bandwidth kept in the cage record."""

    def finish(self, t_start: float, t_end: float) -> None:
        p = self.step.params
        ref = reference_response(self.ctx, self.step)
        reader = self.ctx.open_reader()
        try:
            refs = settled_samples(reader, ref.name, (t_start, t_end), 0.0)
            sent = sent_sines(reader, self.step)
        finally:
            reader.close()
        refs[:, 1:] = to_cage_frame(refs[:, 1:], self.ctx.correction)
        rate = float(p["rate_hz"])
        points: dict[str, list[ResponsePoint]] = {}
        late: dict[str, list[float]] = {}
        for s in segments(p):
            c = commanded(self.step, sent, s)
            if slipped(self.step, sent, s) is not None:
                late.setdefault(AXES[s.axis], []).append(s.f_hz)
            seen = reference_phasor(within(refs, span_of(c, rate)), rate, s.f_hz, s.axis)
            points.setdefault(AXES[s.axis], []).append(
                cage_point(s.f_hz, seen, phasor(c[:, 0], c[:, 1], s.f_hz), ref.at(s.f_hz))
            )
        result = cage_result(points, ref.note(), p, late)
        self.ctx.record_result(self.step.name, result)
        poor = [f"{axis} at {', '.join(f'{f:g}' for f in fs)} Hz"
                for axis, fs in result["poorly_measured_hz"].items() if fs]  # fmt: skip
        if poor:
            self.ctx.event("warning", f"cage_response '{self.step.name}': {'; '.join(poor)} measured"
                           f" no better than {MAX_POINT_SIGMA:g} of the field asked, or their sines"
                           " not made on time (set-points late on a busy computer): not counted in"
                           " the bandwidth; measure again")  # fmt: skip
        record_cage_metrology(self.ctx, self.step.kind, {
            "limit_hz": result["limit_hz"], "bandwidth_hz": result["bandwidth_hz"],
            "amplitude_ut": float(p["amplitude_ut"]), "rate_hz": rate})  # fmt: skip


MAX_POINT_SIGMA = 0.02
"""A point whose amplitude is known no better than this (1-sigma, of the field asked) does not
decide the bandwidth: on a computer too busy to send the set-points on time the staircase is
irregular and the reference's view of it noisy (0.025-0.55 seen under a CPU hog)."""


def cage_result(points: dict[str, list[ResponsePoint]], note: str, params: Mapping[str, Any],
                late_hz: Mapping[str, list[float]] | None = None) -> dict[str, Any]:  # fmt: skip
    """The stored result: per axis the points, the half-power frequency among the points below
    the first one known no better than :data:`MAX_POINT_SIGMA` (None: above half power at every
    one of them), the limit a later sine is held to (the half-power frequency, or the highest of
    those points: nothing beyond is known; None without one), and the frequencies measured too
    poorly to count: known no better than that, or their sines not made on time (``late_hz``
    per axis: set-points that slipped, :func:`rig.steps.sine_fields.slipped`)."""
    bandwidth: dict[str, float | None] = {}
    limit: dict[str, float | None] = {}
    poor: dict[str, list[float]] = {}
    for axis, ps in points.items():
        ordered = sorted(ps, key=lambda q: q.f_hz)
        late = (late_hz or {}).get(axis, [])
        poor[axis] = [q.f_hz for q in ordered
                      if q.amplitude_sigma > MAX_POINT_SIGMA or q.f_hz in late]  # fmt: skip
        # known: the points below the first one measured too poorly (what lies beyond is not)
        known = [q for q in ordered if q.f_hz < min(poor[axis], default=math.inf)]
        bandwidth[axis] = half_power_hz([q.f_hz for q in known], [q.amplitude for q in known])
        top = max((q.f_hz for q in known), default=None)
        limit[axis] = top if bandwidth[axis] is None else bandwidth[axis]
    return {
        "axes": {axis: [{"f_hz": q.f_hz, "amplitude": q.amplitude,
                         "amplitude_sigma": q.amplitude_sigma, "phase_deg": q.phase_deg,
                         "phase_sigma_deg": q.phase_sigma_deg} for q in ps]
                 for axis, ps in points.items()},
        "bandwidth_hz": bandwidth, "limit_hz": limit, "poorly_measured_hz": poor,
        "measured_to_hz": max(float(f) for f in params["frequencies_hz"]),
        "amplitude_ut": float(params["amplitude_ut"]),
        "rate_hz": float(params["rate_hz"]), "reference_response": note,
    }  # fmt: skip


KIND = CageResponse()
