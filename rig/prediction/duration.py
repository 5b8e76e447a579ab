"""How long a procedure will take on the rig: its steps' planned time plus what the plan leaves out.

A field step's dwell starts when the ramp to its set-point ends, so every set-point adds its ramp
(one set-point per ``step_s`` within the slew limit, through zero where a coil's polarity flips:
:func:`rig.cage.limits.plan_ramp`, from the cage model's currents), each polarity flip the wait for
the coil current to decay and the relay to switch, and each trimmed field the closed loop on the
reference. Measured on the simulated cage (the shipped acceptance procedure): the ramps account
for 2.6 of 2.8 s of linearity's extra time and 9.5 of 10.4 s of a 48-point sphere sweep's; the
rest is the flips, about 25 ms each; a trimmed null field took 4.4 s more than its hold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rig.cage.limits import CageLimits, plan_ramp
from rig.cage.model import CageModel
from rig.procedure.plan import compile_step
from rig.steps.vocabulary import FieldCommand, Procedure, RigTiming

FLIP_S = 0.025
"""A polarity flip: the coil current's decay and the relay (s, measured on the simulated cage)."""
TRIM_S = 4.4
"""A trimmed field set-point: the closed loop on the reference (s, measured likewise)."""


@dataclass(frozen=True)
class PredictedDuration:
    """The procedure's planned seconds and what the rig adds: ramps, flips, trims (s)."""

    planned_s: float
    ramps_s: float
    flips: int
    trims: int
    early_stop: bool
    """A live calibration may stop before its ``max_s``: the total is then an upper bound."""
    saved_s: tuple[float, ...] = ()
    """Per noise scenario (each earlier run's), the planned seconds its live steps' predicted
    stops leave out (empty: none predicted)."""

    @property
    def total_s(self) -> float:
        """Everything added up (s): with a live step, the most (each at its ``max_s``)."""
        return self.planned_s + self.ramps_s + self.flips * FLIP_S + self.trims * TRIM_S

    @property
    def expected_s(self) -> float:
        """The typical run's time (s): the live steps stopping where the earlier runs' noises
        predict them to, on average."""
        return self.total_s - (sum(self.saved_s) / len(self.saved_s) if self.saved_s else 0.0)

    @property
    def range_s(self) -> tuple[float, float]:
        """The shortest and longest of the scenarios' times (s)."""
        if not self.saved_s:
            return self.total_s, self.total_s
        return self.total_s - max(self.saved_s), self.total_s - min(self.saved_s)


def predicted_duration(proc: Procedure, model: CageModel | None, limits: CageLimits | None,
                       timing: RigTiming) -> PredictedDuration:  # fmt: skip
    """The procedure's time on the rig; without a cage model or limits only the planned time."""
    planned = ramps = 0.0
    flips = trims = 0
    here = np.zeros(3)
    for step in proc.steps:
        plan = compile_step(step, proc.path.parent, timing)
        planned += plan.duration_s
        for cmd in plan.commands:
            if not isinstance(cmd, FieldCommand):
                continue
            trims += bool(cmd.payload.get("trim"))
            if model is None or limits is None:
                continue
            target = model.currents_a(cmd.payload["field_ut"])
            if cmd.payload.get("track"):
                here = target  # followed within the slew limit, no ramp of its own
                continue
            ramps += len(plan_ramp(here, np.clip(target, -np.array(limits.max_current_a),
                                                 np.array(limits.max_current_a)), limits)) * limits.step_s  # fmt: skip
            flips += int(np.sum(np.sign(here) * np.sign(target) < 0))
            here = target
        if step.kind in ("characterize_cage", "coil_axes", "coil_scalar", "field_map"):
            here = np.zeros(3)  # these steps leave the coils at zero
    early = any(s.kind == "live_calibrate" for s in proc.steps)
    return PredictedDuration(planned, ramps, flips, trims, early)
