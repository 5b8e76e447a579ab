"""``axis_sweep``: evenly spaced fields along one cage axis, each held ``dwell_s``."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from rig.steps.base import Array, FieldStepKind
from rig.steps.vocabulary import RigTiming, Step, StepParam


class AxisSweep(FieldStepKind):
    name = "axis_sweep"
    summary = "evenly spaced fields along one axis"
    params: ClassVar[dict[str, StepParam]] = {
        "axis": StepParam("str", "x", choices=("x", "y", "z")),
        "from_ut": StepParam("float", -50.0),
        "to_ut": StepParam("float", 50.0),
        "points": StepParam("int", 11, 2, 10000),
        "dwell_s": StepParam("float", 0.5, 0.05, 3600.0),
    }

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        p = step.params
        out = []
        for i, v in enumerate(np.linspace(p["from_ut"], p["to_ut"], p["points"])):
            f = np.zeros(3)
            f["xyz".index(p["axis"])] = v
            out.append((i * p["dwell_s"], f))
        return out


KIND = AxisSweep()
