"""``field_points``: a list of fields (uT, cage frame), each held for ``dwell_s``: what ``rig
design`` writes (its D-optimal set-points), or any set a person lists."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from rig.steps.base import Array, FieldStepKind
from rig.steps.vocabulary import RigTiming, Step, StepParam


class FieldPoints(FieldStepKind):
    name = "field_points"
    summary = "hold each field of a list in turn"
    params: ClassVar[dict[str, StepParam]] = {
        "fields_ut": StepParam("list_vec3", required=True, minimum=-1000.0, maximum=1000.0),
        "dwell_s": StepParam("float", 0.8, 0.05, 3600.0),
    }

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        dwell = float(step.params["dwell_s"])
        return [(i * dwell, np.array(f, float)) for i, f in enumerate(step.params["fields_ut"])]


KIND = FieldPoints()
