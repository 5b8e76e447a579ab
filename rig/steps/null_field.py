"""``null_field``: cancel the ambient field and hold; the noise floor of every sampled
magnetometer over the hold is the step's result (``<role>_noise_nt``), and for each one besides
the reference the noise of its pairs with the reference (``<role>_paired_noise_nt``, what a
live calibration sees)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from rig.analysis import noise_floor, paired_noise
from rig.steps.base import Array, FieldStepKind, RunContext, StepExecution
from rig.steps.vocabulary import Param, RigTiming, Step

NOISE_SETTLE_S = 0.3
"""Samples this long after a change are left out of the noise floor (s)."""


class NullField(FieldStepKind):
    name = "null_field"
    summary = "cancel the ambient field, hold, measure every magnetometer's noise floor"
    params: ClassVar[dict[str, Param]] = {
        "hold_s": Param("float", 2.0, 0.0, 86400.0),
        "trim": Param("str", "no", choices=("yes", "no")),
    }
    trim_param = "trim"

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        return [(0.0, np.zeros(3))]

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return float(step.params["hold_s"])

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return NoiseFloor(ctx, step)


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
        finally:
            reader.close()
        result: dict[str, Any] = {
            f"{role}_noise_nt": noise[dev] for role, dev in mags.items() if dev in noise
        }
        result |= {f"{role}_paired_noise_nt": v for role, v in paired.items() if v is not None}
        self.ctx.record_result(self.step.name, result)


KIND = NullField()
