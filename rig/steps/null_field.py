"""``null_field``: cancel the ambient field and hold; the noise floor of every sampled
magnetometer over the hold is the step's result (``<role>_noise_nt``), and for each one besides
the reference the noise of its pairs with the reference (``<role>_paired_noise_nt``, what a
live calibration sees). An untrimmed null with the rig's own cage model (no characterization
earlier in the run) also records the field the reference read there (``null_residual_ut``): the
field that model leaves at a commanded zero, which ``rig check --predict`` adds to the set-points
of later runs with the same model."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from rig.analysis import noise_floor, paired_noise, settled_samples, spread_nt, to_cage_frame
from rig.steps.base import NullHoldKind, RunContext, StepExecution
from rig.steps.vocabulary import Step, StepParam

NOISE_SETTLE_S = 0.3
"""Samples this long after a change are left out of the noise floor (s)."""


@dataclass(frozen=True)
class NoiseFloorResult:
    """A null-field hold's noise: per role, the noise floor (nT, RMS over axes of the standard
    deviation) and, beside the reference, the noise of its pairs with the reference (nT)."""

    noise_nt: dict[str, float]
    paired_noise_nt: dict[str, float]
    null_residual_ut: tuple[float, float, float] | None = None
    """The reference's mean field over the hold (uT, cage frame) when the rig's cage model set
    the null untrimmed; None otherwise."""

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping: ``<role>_noise_nt``, ``<role>_paired_noise_nt`` and (when
        measured) ``null_residual_ut``."""
        out: dict[str, Any] = {f"{role}_noise_nt": v for role, v in self.noise_nt.items()}
        out |= {f"{role}_paired_noise_nt": v for role, v in self.paired_noise_nt.items()}
        if self.null_residual_ut is not None:
            out["null_residual_ut"] = list(self.null_residual_ut)
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> NoiseFloorResult | None:
        """Read a stored result; None when it is not a noise floor."""
        residual = _residual(d.get("null_residual_ut"))
        d = {k: v for k, v in d.items() if k != "null_residual_ut"}
        paired = {k.removesuffix("_paired_noise_nt"): float(v) for k, v in d.items()
                  if k.endswith("_paired_noise_nt")}  # fmt: skip
        noise = {k.removesuffix("_noise_nt"): float(v) for k, v in d.items()
                 if k.endswith("_noise_nt") and not k.endswith("_paired_noise_nt")}  # fmt: skip
        if not noise or len(noise) + len(paired) != len(d):
            return None
        return cls(noise, paired, residual)

    def pair_noise_nt(self, role: str) -> float | None:
        """The noise ``role`` sees paired with the reference (nT): the paired noise measured, else
        (older results) the root sum square of the two floors; None when not measured."""
        if role in self.paired_noise_nt:
            return self.paired_noise_nt[role]
        if role in self.noise_nt:
            return float(np.hypot(self.noise_nt[role], self.noise_nt.get("reference", 0.0)))
        return None


def _residual(value: Any) -> tuple[float, float, float] | None:
    """A stored ``null_residual_ut``: three finite numbers, else None."""
    if not isinstance(value, list | tuple) or len(value) != 3:
        return None
    try:
        x, y, z = (float(v) for v in value)
    except (TypeError, ValueError):
        return None
    return (x, y, z) if all(np.isfinite((x, y, z))) else None


def latest_noise_floor(results: Mapping[str, Any]) -> NoiseFloorResult | None:
    """The newest noise floor among a run's results."""
    for value in reversed(list(results.values())):
        found = NoiseFloorResult.from_dict(value) if isinstance(value, Mapping) else None
        if found is not None:
            return found
    return None


class NullField(NullHoldKind):
    name = "null_field"
    summary = "cancel the ambient field, hold, measure every magnetometer's noise floor"
    result_values = ("*_noise_nt", "*_paired_noise_nt", "null_residual_ut")
    params: ClassVar[dict[str, StepParam]] = {
        "hold_s": StepParam("float", 2.0, 0.0, 86400.0),
        "trim": StepParam("str", "no", choices=("yes", "no")),
    }

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return NoiseFloor(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        found = NoiseFloorResult.from_dict(result) if isinstance(result, Mapping) else None
        if found is None:
            return []
        floors = ", ".join(f"{role} {v:.1f} nT" for role, v in found.noise_nt.items())
        pairs = ", ".join(f"{role} {v:.1f} nT" for role, v in found.paired_noise_nt.items())
        return [
            f"Noise floor '{name}': {floors}"
            + (f"; paired with the reference {pairs}" if pairs else "")
        ]

    def figures(self, reader: Any, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        window = next(((t0, t1) for _, n, _, t0, t1 in reader.steps() if n == name and t1), None)
        if window is None:
            return []
        dut = reader.meta().get("magnetometers", {}).get("dut", "dut")
        # the samples the noise figure is computed from: settled, every ramp and trim left out
        # (issue 55: the plot spanned +-40 000 nT of ramp beside its 21 nT figure)
        rows = settled_samples(reader, dut, window, NOISE_SETTLE_S)
        if len(rows) < 2:
            return []
        fig, ax = plt.subplots(figsize=(9, 3.0))
        for i, axis in enumerate("xyz"):
            ax.plot(rows[:, 0] - window[0], 1000 * (rows[:, 1 + i] - rows[:, 1 + i].mean()), ".-",
                    ms=2, lw=0.6, label=axis)  # fmt: skip
        ax.set_xlabel(f"time in the null-field hold (s); the {len(rows)} settled samples the"
                      f" noise floor ({spread_nt(rows[:, 1:]):.1f} nT) is computed from")  # fmt: skip
        ax.set_ylabel("DUT reading minus mean (nT)")
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        ax.grid(alpha=0.3)
        return [(f"Noise floor at null field ('{name}')", fig)]


class NoiseFloor(StepExecution):
    """After the hold: each magnetometer's noise floor (nT) as the step's result."""

    def finish(self, t_start: float, t_end: float) -> None:
        mags = self.ctx.proc.magnetometers
        ref = mags.get("reference")
        window = (t_start, t_end)
        reader = self.ctx.open_reader()
        try:
            noise = noise_floor(reader, window, list(self.ctx.samplers), NOISE_SETTLE_S)
            paired = {
                role: paired_noise(reader, window, dev, ref, NOISE_SETTLE_S)
                for role, dev in mags.items()
                if ref is not None and role != "reference" and dev in noise and ref in noise
            }
            residual = self._null_residual(reader, ref, window)
        finally:
            reader.close()
        result = NoiseFloorResult(
            {role: noise[dev] for role, dev in mags.items() if dev in noise},
            {role: v for role, v in paired.items() if v is not None},
            residual,
        )
        self.ctx.record_result(self.step.name, result.to_dict())
        self.ctx.predict_after_null(self.step.name)

    def _null_residual(self, reader: Any, ref: str | None,
                       window: tuple[float, float]) -> tuple[float, float, float] | None:  # fmt: skip
        """The reference's mean over the hold (uT, cage frame) when the rig's own cage model set
        this null untrimmed (no characterization earlier in the run); else None."""
        from rig.steps import cage_model_measured_before  # the registry (it imports this module)

        characterized = cage_model_measured_before(self.ctx.proc, self.step)
        if ref is None or characterized or self.step.params.get("trim") == "yes":
            return None
        t_a, t_b = window[0] + NOISE_SETTLE_S, window[1]
        rows = np.array([r[1:4] for r in reader.samples(ref) if t_a <= r[0] <= t_b], float)
        if rows.shape[0] == 0:
            return None
        x, y, z = (float(v) for v in to_cage_frame(rows, self.ctx.correction).mean(axis=0))
        return (x, y, z)


KIND = NullField()
