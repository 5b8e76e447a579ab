"""``rotate``: a field of fixed magnitude turning about an axis in ``points`` steps."""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from rig.steps.base import Array, FieldStepKind
from rig.steps.vocabulary import ProcedureError, RigTiming, Step, StepParam


class Rotate(FieldStepKind):
    name = "rotate"
    summary = "a field turning about an axis"
    params: ClassVar[dict[str, StepParam]] = {
        "magnitude_ut": StepParam("float", 40.0, 0.0, 1000.0),
        "axis": StepParam("vec3", [0.0, 0.0, 1.0]),
        "points": StepParam("int", 36, 3, 10000),
        "dwell_s": StepParam("float", 0.3, 0.02, 3600.0),
    }

    def validate(self, params: dict[str, object], loads: tuple[str, ...], where: str) -> None:
        if not any(float(v) for v in params["axis"]):  # type: ignore[attr-defined]
            raise ProcedureError(f"{where}: axis must not be zero, e.g. [0, 0, 1]")

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        p = step.params
        spin = np.array(p["axis"], float)
        spin /= np.linalg.norm(spin)
        helper = np.array([1.0, 0, 0]) if abs(spin[0]) < 0.9 else np.array([0, 1.0, 0])
        u = np.cross(spin, helper)
        u /= np.linalg.norm(u)
        v = np.cross(spin, u)
        angles = np.linspace(0, 2 * math.pi, p["points"], endpoint=False)
        return [
            (i * p["dwell_s"], p["magnitude_ut"] * (math.cos(a) * u + math.sin(a) * v))
            for i, a in enumerate(angles)
        ]


KIND = Rotate()
