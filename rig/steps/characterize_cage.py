"""``characterize_cage``: measure the cage's field per ampere on every axis with the reference
magnetometer (the cage model), save it and use it for the rest of the run."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from rig import stored
from rig.steps.base import StepExecution, StepKind
from rig.steps.vocabulary import RigTiming, Step, StepParam

if TYPE_CHECKING:
    from rig.cage.model import CageModel

Matrix3 = tuple[tuple[float, ...], ...]


@dataclass(frozen=True)
class CageCharacterizationResult:
    """A cage characterization's result: the cage model ``B = K I + B0`` with 1-sigma, as the rest
    of the run uses it (the full model, with its date and instruments, is the run's ``cage_model``
    meta and the saved calibration file)."""

    k_ut_per_a: Matrix3
    """K: the field per coil current (uT/A), rows the field axes, columns the coils."""
    b0_ut: tuple[float, ...]
    """B0: the ambient field in the cage with the coils off (uT)."""
    k_sigma_ut_per_a: Matrix3
    """1-sigma of each element of K (uT/A)."""
    b0_sigma_ut: tuple[float, ...]
    """1-sigma of B0 (uT)."""
    residual_rms_nt: float
    """RMS of the fit's residuals (nT)."""
    condition_number: float
    """Of K (ratio): how well the three coils span the three field axes."""

    @classmethod
    def from_model(cls, model: CageModel) -> CageCharacterizationResult:
        """The result of a freshly characterized model."""
        return cls(
            tuple(tuple(row) for row in model.k_ut_per_a.tolist()), tuple(model.b0_ut.tolist()),
            tuple(tuple(row) for row in model.k_sigma.tolist()), tuple(model.b0_sigma_ut.tolist()),
            model.meta["residual_rms_nt"], model.meta["condition_number"],
        )  # fmt: skip

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping."""
        return {
            "k_ut_per_a": [list(row) for row in self.k_ut_per_a], "b0_ut": list(self.b0_ut),
            "k_sigma_ut_per_a": [list(row) for row in self.k_sigma_ut_per_a],
            "b0_sigma_ut": list(self.b0_sigma_ut),
            "residual_rms_nt": self.residual_rms_nt, "condition_number": self.condition_number,
        }  # fmt: skip

    @classmethod
    def from_dict(cls, d: Any) -> CageCharacterizationResult:
        """Read a stored characterization result; a :class:`~rig.errors.StoredResultError` names
        what is wrong."""
        what = "cage characterization result"
        d = stored.mapping(d, what)
        return cls(
            stored.matrix3(d, "k_ut_per_a", what), stored.numbers(d, "b0_ut", what, 3),
            stored.matrix3(d, "k_sigma_ut_per_a", what), stored.numbers(d, "b0_sigma_ut", what, 3),
            stored.number(d, "residual_rms_nt", what), stored.number(d, "condition_number", what),
        )  # fmt: skip


def characterization_duration_s(
    amplitude_a: float, samples: int, repeats: int, timing: RigTiming | None = None
) -> float:
    """Estimated wall time of ``characterize_cage`` (s): per sweep point the ramp (one set-point per
    ``step_s``, within the slew limit, through zero where the polarity flips), the transient wait
    and ``samples`` fresh reference readings (plus on average half a period until the first); then
    the ramp back to zero. Within 5 % of the measured time on the simulated cage (docs/procedures.md)."""
    from rig.cage.characterize import TRANSIENT_S, sweep_points  # the sweep itself, not a copy
    from rig.cage.limits import CageLimits, plan_ramp

    t = timing or RigTiming()
    big = 1e6  # the planner checks current limits; the dry run checks them elsewhere
    limits = CageLimits((big, big, big), big, t.max_slew_a_per_s, t.step_s)
    points = np.tile(sweep_points(amplitude_a), (repeats, 1))
    here = np.zeros(3)
    setpoints = 0
    for target in [*points, np.zeros(3)]:
        setpoints += len(plan_ramp(here, target, limits))
        here = target
    per_point = TRANSIENT_S + (samples + 0.5) / t.reference_rate_hz
    return setpoints * t.step_s + len(points) * per_point


class CharacterizeCage(StepKind):
    name = "characterize_cage"
    summary = "measure the cage's uT per A on every axis (the cage model)"
    result_values = ("residual_rms_nt", "condition_number")
    measures_cage_model = True
    params: ClassVar[dict[str, StepParam]] = {
        "amplitude_a": StepParam("float", 1.0, 0.01, 100.0),
        "samples": StepParam("int", 10, 1, 10000),
        "repeats": StepParam("int", 2, 1, 20),
    }

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        p = step.params
        return characterization_duration_s(p["amplitude_a"], p["samples"], p["repeats"], timing)

    def peak_coil_current_a(self, step: Step) -> float | None:
        return float(step.params["amplitude_a"])  # +-amplitude on every axis

    def execution(self, ctx: Any, step: Any) -> StepExecution:
        return Characterize(ctx, step)


class Characterize(StepExecution):
    def run(self, payload: dict[str, Any]) -> None:
        from rig.cage.characterize import characterize

        ctx = self.ctx
        model = characterize(ctx.controller, payload["amplitude_a"], samples=payload["samples"],
                             repeats=payload["repeats"])  # fmt: skip
        previous = getattr(ctx.controller, "model", None)
        for kind, entry in (previous.metrology() if previous else {}).items():  # kept in the record
            model = model.with_metrology(kind, entry)
        ctx.controller.model = model
        if ctx.cfg.cage is not None and ctx.cfg.cage.calibration is not None:
            version = model.save(ctx.cfg.cage.calibration)
            model.meta["file"] = str(version)
        ctx.set_meta(cage_model=model.to_dict())
        ctx.record_result(self.step.name, CageCharacterizationResult.from_model(model).to_dict())


KIND = CharacterizeCage()
