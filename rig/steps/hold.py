"""``hold``: keep the present field for ``hold_s`` (load profiles may run meanwhile)."""

from __future__ import annotations

from typing import ClassVar

from rig.steps.base import Array, FieldStepKind
from rig.steps.vocabulary import RigTiming, Step, StepParam


class Hold(FieldStepKind):
    name = "hold"
    summary = "keep the present field"
    params: ClassVar[dict[str, StepParam]] = {
        "hold_s": StepParam("float", required=True, minimum=0.0, maximum=86400.0)
    }

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        return []

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return float(step.params["hold_s"])


KIND = Hold()
