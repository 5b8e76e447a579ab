"""``set_field``: ramp to one field (uT, cage frame) and hold it."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from rig.steps.base import Array, FieldStepKind
from rig.steps.vocabulary import RigTiming, Step, StepParam


class SetField(FieldStepKind):
    name = "set_field"
    summary = "ramp to one field and hold it"
    params: ClassVar[dict[str, StepParam]] = {
        "field_ut": StepParam("vec3", required=True),
        "hold_s": StepParam("float", 2.0, 0.0, 86400.0),
        "trim": StepParam("str", "no", choices=("yes", "no")),
    }
    trim_param = "trim"

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        return [(0.0, np.array(step.params["field_ut"], float))]

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return float(step.params["hold_s"])


KIND = SetField()
