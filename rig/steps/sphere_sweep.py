"""``sphere_sweep``: fields in nearly uniform directions and spread magnitudes, each held
``dwell_s`` (the data of a full calibration)."""

from __future__ import annotations

from typing import ClassVar

from rig.steps.base import Array, FieldStepKind
from rig.steps.geometry import sphere_fields
from rig.steps.vocabulary import RigTiming, Step, StepParam


class SphereSweep(FieldStepKind):
    name = "sphere_sweep"
    summary = "fields in nearly uniform directions, each held dwell_s"
    params: ClassVar[dict[str, StepParam]] = {
        "directions": StepParam("int", 40, 4, 10000),
        "magnitude_ut": StepParam("range2", [30.0, 30.0], 0.0, 1000.0),
        "dwell_s": StepParam("float", 0.5, 0.05, 3600.0),
        "seed": StepParam("int", 1, 0, 2**31),
    }

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        p = step.params
        fields = sphere_fields(p["directions"], p["magnitude_ut"], p["seed"])
        return [(i * p["dwell_s"], f) for i, f in enumerate(fields)]


KIND = SphereSweep()
