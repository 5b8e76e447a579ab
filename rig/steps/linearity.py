"""``linearity``: sweep the field along each cage axis from -max to +max (by default the rig's field
limit) and measure how far the DUT's reading departs from a straight line against the reference:
the largest deviation in ppm of full scale (max_ut), per axis and overall.

Each point's DUT and reference readings are averaged over its settled dwell; per axis the DUT's
component along that axis is fitted as offset + gain x reference component (least squares), and the
residuals are the non-linearity.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from rig import stored
from rig.analysis import change_times, settled_samples, to_cage_frame
from rig.errors import RigError
from rig.steps.base import (
    MAX_EXTRA_HOLD_S,
    Array,
    FieldStepKind,
    RunContext,
    SettledNeed,
    StepExecution,
)
from rig.steps.vocabulary import DEFAULT_FIELD_LIMIT_UT, RigTiming, Step, StepParam

MIN_PER_POINT = 3
"""Settled samples a point needs from each magnetometer."""


def full_scale_ut(step: Step, timing: RigTiming) -> float:
    """The sweep's largest field (uT): ``max_ut``, else the rig's field limit."""
    given = float(step.params["max_ut"])
    return given or timing.max_field_ut or DEFAULT_FIELD_LIMIT_UT


def nonlinearity(applied_ut: Array, reading_ut: Array) -> tuple[Array, float, float]:
    """Residuals (uT) of ``reading = offset + gain * applied`` (least squares), and the gain and
    offset (uT)."""
    design = np.column_stack([np.ones_like(applied_ut), applied_ut])
    coef, *_ = np.linalg.lstsq(design, reading_ut, rcond=None)
    return reading_ut - design @ coef, float(coef[1]), float(coef[0])


@dataclass(frozen=True)
class AxisLinearity:
    """One axis's sweep: per settled point the applied field (uT, the reference's component along
    the axis) and the DUT's departure from its straight line (uT); the line's gain and offset."""

    applied_ut: tuple[float, ...]
    residual_ut: tuple[float, ...]
    gain: float
    """DUT reading per applied field (ratio); stored as a one-element list."""
    offset_ut: float
    """The line's DUT reading at zero applied field (uT); stored as a one-element list."""

    def to_dict(self) -> dict[str, list[float]]:
        """The stored mapping of one axis."""
        return {"applied_ut": list(self.applied_ut), "residual_ut": list(self.residual_ut),
                "gain": [self.gain], "offset_ut": [self.offset_ut]}  # fmt: skip

    @classmethod
    def from_dict(cls, d: Any, what: str) -> AxisLinearity:
        """Read one axis's stored mapping (``what`` names it in an error)."""
        d = stored.mapping(d, what)
        applied = stored.numbers(d, "applied_ut", what)
        residual = stored.numbers(d, "residual_ut", what, len(applied))
        (gain,) = stored.numbers(d, "gain", what, 1)
        (offset,) = stored.numbers(d, "offset_ut", what, 1)
        return cls(applied, residual, gain, offset)


@dataclass(frozen=True)
class LinearityResult:
    """A linearity sweep's result: the largest departure from a straight line in ppm of full scale
    (worst axis, and per axis x, y, z), the full scale (uT) and each axis's points."""

    nonlinearity_ppm: float
    axis_nonlinearity_ppm: dict[str, float]
    full_scale_ut: float
    """The sweep's largest commanded field (uT), the scale the ppm are of."""
    points: dict[str, AxisLinearity]

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping."""
        return {"nonlinearity_ppm": self.nonlinearity_ppm,
                "axis_nonlinearity_ppm": dict(self.axis_nonlinearity_ppm),
                "full_scale_ut": self.full_scale_ut,
                "points": {a: p.to_dict() for a, p in self.points.items()}}  # fmt: skip

    @classmethod
    def from_dict(cls, d: Any) -> LinearityResult:
        """Read a stored linearity result; a :class:`StoredResultError` names what is wrong."""
        what = "linearity result"
        d = stored.mapping(d, what)
        points = stored.mapping(stored.entry(d, "points", what), f"{what} 'points'")
        return cls(
            stored.number(d, "nonlinearity_ppm", what),
            stored.number_map(d, "axis_nonlinearity_ppm", what),
            stored.number(d, "full_scale_ut", what),
            {str(a): AxisLinearity.from_dict(p, f"{what} axis {a}") for a, p in points.items()},
        )


def read_linearity(result: Any) -> LinearityResult | None:
    """A stored result as a linearity result; None when it is not one (the report then lists the
    result's numbers, as for any result its kind does not describe)."""
    return stored.read_or_none(LinearityResult.from_dict, result)


class Linearity(FieldStepKind):
    name = "linearity"
    summary = "sweep each axis to the field limit; deviation from linear in ppm of full scale"
    result_values = ("nonlinearity_ppm", "axis_nonlinearity_ppm.*", "full_scale_ut")
    params: ClassVar[dict[str, StepParam]] = {
        "max_ut": StepParam("float", 0.0, 0.0, 1000.0),
        "points": StepParam("int", 9, 5, 1001),
        "dwell_s": StepParam("float", 0.6, 0.1, 3600.0),
        "settle_s": StepParam("float", 0.25, 0.0, 60.0),
        "magnetometer": StepParam("str", "dut"),
    }

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        p = step.params
        out: list[tuple[float, Array]] = []
        for axis in range(3):
            for v in np.linspace(
                -full_scale_ut(step, timing), full_scale_ut(step, timing), p["points"]
            ):
                f = np.zeros(3)
                f[axis] = v
                out.append((len(out) * p["dwell_s"], f))
        return out

    def settled_need(self, step: Step, magnetometers: Mapping[str, str]) -> SettledNeed:
        dut = magnetometers.get(step.params["magnetometer"], step.params["magnetometer"])
        devices = (dut, magnetometers["reference"]) if "reference" in magnetometers else (dut,)
        return SettledNeed(devices, MIN_PER_POINT, float(step.params["settle_s"]))

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return MeasureLinearity(ctx, step)

    def figures(self, reader: Any, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        found = read_linearity(result)
        if found is None:
            return []
        fig, ax = plt.subplots(figsize=(7.0, 3.6))
        for axis, pts in found.points.items():
            ppm = found.axis_nonlinearity_ppm.get(axis, float("nan"))
            ax.plot(np.array(pts.applied_ut), 1000.0 * np.array(pts.residual_ut), "o-", ms=3,
                    lw=0.8, label=f"{axis}: {ppm:.0f} ppm")  # fmt: skip
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_xlabel("applied field along the axis (uT, reference)")
        ax.set_ylabel("DUT minus straight line (nT)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the axes
        return [(f"Linearity '{name}' (full scale {found.full_scale_ut:g} uT)", fig)]

    def report_lines(self, name: str, result: Any) -> list[str]:
        found = read_linearity(result)
        if found is None:
            return []
        axes = ", ".join(f"{a} {v:.0f}" for a, v in found.axis_nonlinearity_ppm.items())
        return [
            f"Linearity {name}: {found.nonlinearity_ppm:.0f} ppm of"
            f" {found.full_scale_ut:g} uT full scale (worst axis; per axis {axes} ppm)."
        ]


class MeasureLinearity(StepExecution):
    def finish(self, t_start: float, t_end: float) -> None:
        ctx, p = self.ctx, self.step.params
        mags = ctx.proc.magnetometers
        dut = mags.get(p["magnetometer"], p["magnetometer"])
        ref = mags.get("reference")
        if ref is None:
            raise RigError(f"{ctx.proc.path}: linearity needs a 'reference' under 'magnetometers'")
        reader = ctx.open_reader()
        try:
            fields = [(t, pl) for t, _, kind, pl in reader.commands()
                      if kind == "field" and t_start <= t <= t_end]  # fmt: skip
            bounds = [t for t, _ in fields[1:]] + [t_end]
            changes = change_times(reader)
            dut_rows = settled_samples(reader, dut, (t_start, t_end), p["settle_s"], changes)
            ref_rows = settled_samples(reader, ref, (t_start, t_end), p["settle_s"], changes)
        finally:
            reader.close()
        points: dict[str, AxisLinearity] = {}
        ppm: dict[str, float] = {}
        scale = float(max(abs(v) for _, pl in fields for v in pl["field_ut"])) if fields else 0.0
        for axis, name in enumerate("xyz"):
            applied, reading = [], []
            for i, ((t0, _), t1) in enumerate(zip(fields, bounds, strict=True)):
                if i // p["points"] != axis:  # the sweeps go x, y, z in turn
                    continue
                d = dut_rows[(dut_rows[:, 0] >= t0) & (dut_rows[:, 0] < t1)]
                r = ref_rows[(ref_rows[:, 0] >= t0) & (ref_rows[:, 0] < t1)]
                if len(d) < MIN_PER_POINT or len(r) < MIN_PER_POINT:
                    continue
                applied.append(float(to_cage_frame(r[:, 1:], ctx.correction).mean(axis=0)[axis]))
                reading.append(float(d[:, 1 + axis].mean()))
            if len(applied) < 5:
                raise RigError(
                    f"linearity '{self.step.name}': only {len(applied)} settled points on axis {name}"
                    f" (at least 5), although each field was held up to {MAX_EXTRA_HOLD_S:g} s"
                    f" longer for its {MIN_PER_POINT} settled samples per magnetometer: a sensor"
                    " sends too slowly or stalled (see the run's log), or settle_s leaves too little"
                    " of dwell_s"
                )
            residual, gain, offset = nonlinearity(np.array(applied), np.array(reading))
            ppm[name] = float(1e6 * np.max(np.abs(residual)) / scale)
            points[name] = AxisLinearity(tuple(applied), tuple(residual.tolist()), gain, offset)
        result = LinearityResult(max(ppm.values()), ppm, scale, points)
        ctx.record_result(self.step.name, result.to_dict())


KIND = Linearity()
