"""Cage limits and the ramp planner: every set-point sequence the rig sends is planned here.

The planner is pure (no I/O) so that a property test can show that no command sequence produces
a set-point beyond a limit or a step faster than the slew limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from rig.config import coil_step_a
from rig.errors import RigError

Array = npt.NDArray[np.float64]


class CageLimitError(RigError):
    """A command would exceed a cage limit; nothing was sent."""


@dataclass(frozen=True)
class CageLimits:
    """Hard limits: per-axis coil current (A), field magnitude (uT), current slew rate (A/s)."""

    max_current_a: tuple[float, float, float]
    max_field_ut: float
    max_slew_a_per_s: float
    step_s: float = 0.05  # interval between ramp set-points
    coil_tau_s: float | None = None
    """The coils' (shortest) L/R (s): a set-point step into a first-order coil makes its current
    change fastest right after the step, so with it the steps are sized for that peak slope,
    not only for the average."""

    def __post_init__(self) -> None:
        if min(self.max_current_a) <= 0 or self.max_field_ut <= 0 or self.max_slew_a_per_s <= 0:
            raise ValueError("cage limits must be positive")
        if self.step_s <= 0:
            raise ValueError("step_s must be positive")
        if self.coil_tau_s is not None and not self.coil_tau_s > 0:
            raise ValueError("coil_tau_s must be positive")

    @property
    def max_step_a(self) -> float:
        """Largest change of one axis between consecutive set-points (A)."""
        return self.step_within_a(self.step_s)

    def step_within_a(self, dt_s: float) -> float:
        """The largest set-point change (A) ``dt_s`` after the last one that keeps the coil
        current's slope within ``max_slew_a_per_s`` (:func:`rig.config.coil_step_a`)."""
        return coil_step_a(self.max_slew_a_per_s, dt_s, self.coil_tau_s)

    def check_currents(self, currents_a: npt.ArrayLike, what: str = "command") -> None:
        """Refuse currents beyond the per-axis limits."""
        i = np.asarray(currents_a, float)
        for axis in range(3):
            if abs(i[axis]) > self.max_current_a[axis] + 1e-12:
                raise CageLimitError(
                    f"{what} needs {i[axis]:+.3f} A on axis {'xyz'[axis]}, beyond the"
                    f" {self.max_current_a[axis]:g} A limit: ask for a smaller field"
                )

    def check_field(self, field_ut: npt.ArrayLike, what: str = "command") -> None:
        """Refuse a field magnitude beyond the limit."""
        mag = float(np.linalg.norm(np.asarray(field_ut, float)))
        if mag > self.max_field_ut + 1e-9:
            raise CageLimitError(
                f"{what}: |B| = {mag:.1f} uT is beyond the {self.max_field_ut:g} uT field limit"
            )


def plan_ramp(start_a: npt.ArrayLike, target_a: npt.ArrayLike, limits: CageLimits) -> list[Array]:
    """Set-points from ``start_a`` to ``target_a``, one per ``limits.step_s``.

    * Axes whose magnitude decreases move first, then the increasing ones, so the field never
      overshoots the larger of the start and target fields by ramp ordering.
    * An axis that changes sign ramps to zero first (the polarity can then be switched at zero).
    * No axis moves more than ``max_step_a`` between consecutive set-points.
    * The target is checked against the current limits before anything is planned.
    """
    start = np.asarray(start_a, float).copy()
    target = np.asarray(target_a, float)
    limits.check_currents(target, "target")
    limits.check_currents(start, "present state")
    through_zero = np.sign(start) * np.sign(target) < 0
    intermediate = np.where(through_zero, 0.0, target)
    decreasing = np.abs(intermediate) < np.abs(start)
    phases = [
        np.where(decreasing, intermediate, start),  # 1: shrink (and go to zero where flipping)
        intermediate,  # 2: grow axes that do not change sign
        target,  # 3: grow flipped axes from zero with the new polarity
    ]
    points: list[Array] = []
    here = start
    for goal in phases:
        delta = goal - here
        steps = 0
        if np.any(delta):
            steps = max(1, math.ceil(float(np.max(np.abs(delta))) / limits.max_step_a - 1e-9))
        for k in range(1, steps + 1):
            points.append(here + delta * (k / steps))
        here = goal.copy()
    return points
