"""``supply_stability``: hold a coil field and measure how it drifts, with the lab field's changes
taken out by the cage's outside reference (``[cage] ambient``).

The supplies report the current they were set to; only the field shows their gain drifting (a
shunt warming, ageing). Over the hold the inner reference reads ``coils(t) + lab(t)`` and the
outside one ``lab'(t)`` plus a constant (another place: the offset between the two is fitted,
never assumed); the difference's trend is the coils' drift. Per axis the result gives that drift
(nT/h) with a sigma valid for correlated residuals (Newey-West with Andrews' bandwidth,
:mod:`rig.calibration.correlated`), the drift of the inner reference alone for comparison, and
the residual ambient error: the scatter left about the trend with and without the subtraction.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from rig import stored
from rig.errors import RigError
from rig.steps.base import Array, FieldStepKind, RunContext, StepExecution, record_cage_metrology
from rig.steps.vocabulary import RigTiming, Step, StepParam

AXES = ("x", "y", "z")
SETTLE_S = 2.0
"""Samples this long after the field (or a load) changed are left out (s): coil and trim
transients (:func:`rig.analysis.settled_samples`)."""
BLOCK_S = 10.0
"""The residual scatter is of means over this long (s): the slow error that holding a field
suffers, not the sensors' white noise (which the subtraction can only add to)."""


def slow_scatter(t_s: Array, resid: Array) -> float:
    """Standard deviation of the means of ``resid`` over consecutive ``BLOCK_S`` blocks."""
    block = np.floor((t_s - t_s[0]) / BLOCK_S).astype(int)
    counts = np.bincount(block)
    means = np.bincount(block, weights=resid)[counts > 0] / counts[counts > 0]
    return float(np.std(means)) if means.size > 1 else float("nan")


def trend(t_s: Array, y: Array) -> tuple[float, float, Array]:
    """Slope (per s) of ``y`` against ``t_s``, its 1-sigma for correlated residuals and the
    residuals about the line."""
    from rig.calibration.correlated import andrews_bandwidth, long_run_covariance

    x = np.column_stack([np.ones_like(t_s), t_s - t_s.mean()])
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    resid = y - x @ coef
    n = len(y)
    rho = float(np.corrcoef(resid[:-1], resid[1:])[0, 1]) if n > 3 else 0.0
    scores = x * resid[:, None]
    omega = long_run_covariance(lambda rows: scores[rows], n, andrews_bandwidth(rho, n))
    xtx_inv = np.linalg.inv(x.T @ x)
    cov = xtx_inv @ (n * omega) @ xtx_inv * n / max(n - 2, 1)
    return float(coef[1]), float(np.sqrt(max(cov[1, 1], 0.0))), resid


@dataclass(frozen=True)
class SupplyStabilityResult:
    """Per axis (cage frame): the coils' field drift with the lab field's changes taken out and its
    1-sigma (nT/h), the inner reference's own drift (nT/h), and the scatter about the trend of
    10 s means with and without the outside reference (nT rms): the residual ambient error."""

    drift_nt_per_h: dict[str, float]
    drift_sigma_nt_per_h: dict[str, float]
    reference_drift_nt_per_h: dict[str, float]
    residual_nt: dict[str, float]
    reference_residual_nt: dict[str, float]
    hold_s: float

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping."""
        return {"drift_nt_per_h": self.drift_nt_per_h,
                "drift_sigma_nt_per_h": self.drift_sigma_nt_per_h,
                "reference_drift_nt_per_h": self.reference_drift_nt_per_h,
                "residual_nt": self.residual_nt, "reference_residual_nt": self.reference_residual_nt,
                "hold_s": self.hold_s}  # fmt: skip

    @classmethod
    def from_dict(cls, d: Any) -> SupplyStabilityResult:
        """Read a stored result; a :class:`~rig.errors.StoredResultError` names what is wrong."""
        what = "supply stability result"
        d = stored.mapping(d, what)
        maps = [stored.number_map(d, k, what) for k in (
            "drift_nt_per_h", "drift_sigma_nt_per_h", "reference_drift_nt_per_h", "residual_nt",
            "reference_residual_nt")]  # fmt: skip
        return cls(maps[0], maps[1], maps[2], maps[3], maps[4], stored.number(d, "hold_s", what))


class SupplyStability(FieldStepKind):
    name = "supply_stability"
    summary = (
        "hold a coil field; its drift with the lab field's changes taken out (outside reference)"
    )
    result_values = ("drift_nt_per_h.*", "drift_sigma_nt_per_h.*", "residual_nt.*")
    params: ClassVar[dict[str, StepParam]] = {
        "field_ut": StepParam("vec3", [0.0, 0.0, 40.0]),
        "hold_s": StepParam("float", 600.0, 10.0, 86400.0),
    }

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        return [(0.0, np.asarray(step.params["field_ut"], float))]

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return float(step.params["hold_s"])

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return DriftWatch(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        found = SupplyStabilityResult.from_dict(result) if isinstance(result, Mapping) else None
        if found is None:
            return []
        drift = ", ".join(f"{a} {found.drift_nt_per_h[a]:+.1f} +- {found.drift_sigma_nt_per_h[a]:.1f}"
                          for a in AXES)  # fmt: skip
        raw = ", ".join(f"{a} {found.reference_drift_nt_per_h[a]:+.1f}" for a in AXES)
        return [f"Supply stability '{name}' over {found.hold_s:.0f} s: the coils' field drifts"
                f" {drift} nT/h with the lab field's changes taken out (the inner reference"
                f" alone: {raw} nT/h); scatter of 10 s means about the trend"
                f" {max(found.residual_nt.values()):.2f} nT (without the outside reference"
                f" {max(found.reference_residual_nt.values()):.2f} nT)"]  # fmt: skip


class DriftWatch(StepExecution):
    """After the hold: the drift of the inner reference less the outside one."""

    def finish(self, t_start: float, t_end: float) -> None:
        from rig.analysis import change_times, settled_samples, to_cage_frame

        cage = self.ctx.cfg.cage
        inner = self.ctx.proc.magnetometers.get("reference")
        outside = cage.ambient if cage is not None else None
        if inner is None or outside is None:
            raise RigError(f"step '{self.step.name}': the drift of the coils needs the"
                           " procedure's reference and the rig's outside reference ([cage] ambient"
                           " in the rig configuration)")  # fmt: skip
        reader = self.ctx.open_reader()
        try:
            changes = change_times(reader)
            rows = [settled_samples(reader, dev, (t_start, t_end), SETTLE_S, changes)
                    for dev in (inner, outside)]  # fmt: skip
        finally:
            reader.close()
        ref, out = rows
        if len(ref) < 10 or len(out) < 10:
            raise RigError(f"step '{self.step.name}': too few readings in the hold ({len(ref)}"
                           f" inside, {len(out)} outside): lengthen hold_s")  # fmt: skip
        t = ref[:, 0]
        inner_ut = to_cage_frame(ref[:, 1:], self.ctx.correction)
        outside_ut = np.column_stack([np.interp(t, out[:, 0], out[:, 1 + i]) for i in range(3)])
        result = _result(t, inner_ut, outside_ut, t_end - t_start).to_dict()
        self.ctx.record_result(self.step.name, result)
        record_cage_metrology(self.ctx, self.step.kind, {"result": result})


def _result(t: Array, inner_ut: Array, outside_ut: Array, hold_s: float) -> SupplyStabilityResult:
    out: dict[str, dict[str, float]] = {k: {} for k in ("d", "s", "r", "res", "rres")}
    for i, axis in enumerate(AXES):
        slope, sigma, resid = trend(t, inner_ut[:, i] - outside_ut[:, i])
        raw, _, raw_resid = trend(t, inner_ut[:, i])
        out["d"][axis], out["s"][axis] = 3.6e6 * slope, 3.6e6 * sigma
        out["r"][axis] = 3.6e6 * raw
        out["res"][axis] = 1000.0 * slow_scatter(t, resid)
        out["rres"][axis] = 1000.0 * slow_scatter(t, raw_resid)
    return SupplyStabilityResult(out["d"], out["s"], out["r"], out["res"], out["rres"], hold_s)


KIND = SupplyStability()
