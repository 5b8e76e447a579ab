"""``coil_axes``: the coil constants and the angles between the coil axes to arcseconds, with the
reference turned on a rotation fixture by the operator (the vector method, :mod:`rig.cage.coil_axes`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from rig import stored
from rig.errors import RigError
from rig.steps.base import StepExecution, StepKind, ask_or_abort, record_cage_metrology
from rig.steps.vocabulary import RigTiming, Step, StepParam

AXES = ("x", "y", "z")
PAIRS = ("xy", "xz", "yz")


@dataclass(frozen=True)
class CoilAxesResult:
    """What the vector method found, each with its 1-sigma."""

    constants_ut_per_a: dict[str, float]
    """|K_j|: each coil's field per ampere (uT/A)."""
    constants_sigma_ppm: dict[str, float]
    """1-sigma of each coil constant, relative (ppm)."""
    skew_arcsec: dict[str, float]
    """The angle between two coil axes minus 90 degrees (arcsec), per pair."""
    skew_sigma_arcsec: dict[str, float]
    """1-sigma of each skew (arcsec)."""
    k_ut_per_a: tuple[tuple[float, ...], ...]
    """K in the fixture's base frame: columns the coils (uT/A)."""
    chi2_per_dof: float
    """The fit's chi-square per degree of freedom (1 when the readings scatter as they say)."""
    notes: tuple[str, ...]

    @classmethod
    def from_fit(cls, fit: Any) -> CoilAxesResult:
        """The result of :func:`rig.cage.coil_axes.fit_coil_axes`."""
        const = fit.constants_ut_per_a
        return cls(
            dict(zip(AXES, map(float, const), strict=True)),
            dict(zip(AXES, map(float, 1e6 * fit.constants_sigma / const), strict=True)),
            dict(zip(PAIRS, map(float, fit.skew_arcsec), strict=True)),
            dict(zip(PAIRS, map(float, fit.skew_sigma_arcsec), strict=True)),
            tuple(tuple(row) for row in fit.k_ut_per_a.tolist()),
            fit.chi2 / max(fit.dof, 1), tuple(fit.notes),
        )  # fmt: skip

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping."""
        return {
            "constants_ut_per_a": self.constants_ut_per_a,
            "constants_sigma_ppm": self.constants_sigma_ppm,
            "skew_arcsec": self.skew_arcsec, "skew_sigma_arcsec": self.skew_sigma_arcsec,
            "k_ut_per_a": [list(row) for row in self.k_ut_per_a],
            "chi2_per_dof": self.chi2_per_dof, "notes": list(self.notes),
        }  # fmt: skip

    @classmethod
    def from_dict(cls, d: Any) -> CoilAxesResult:
        """Read a stored result; a :class:`~rig.errors.StoredResultError` names what is wrong."""
        what = "coil axes result"
        d = stored.mapping(d, what)
        return cls(
            stored.number_map(d, "constants_ut_per_a", what),
            stored.number_map(d, "constants_sigma_ppm", what),
            stored.number_map(d, "skew_arcsec", what),
            stored.number_map(d, "skew_sigma_arcsec", what),
            stored.matrix3(d, "k_ut_per_a", what), stored.number(d, "chi2_per_dof", what),
            tuple(str(n) for n in d.get("notes", [])),
        )  # fmt: skip


def coil_axes_duration_s(step: Step, timing: RigTiming) -> float:
    """Cage time of the step (s), the operator's turns not counted: per position and coil the
    ramps to +I, -I, +I and back (within the slew limit), the transient and the readings."""
    from rig.cage.characterize import TRANSIENT_S
    from rig.cage.coil_axes import DEFAULT_POSITIONS
    from rig.cage.limits import CageLimits, plan_ramp

    amps, samples = float(step.params["amplitude_a"]), int(step.params["samples"])
    big = 1e6
    limits = CageLimits((big, big, big), big, timing.max_slew_a_per_s, timing.step_s)
    setpoints, here = 0, np.zeros(3)
    for coil in range(3):
        for sign in (1.0, -1.0, 1.0, 0.0):
            target = np.zeros(3)
            target[coil] = sign * amps
            setpoints += len(plan_ramp(here, target, limits))
            here = target
    per_level = TRANSIENT_S + (samples + 0.5) / timing.reference_rate_hz
    per_position = setpoints * timing.step_s + 9 * per_level
    return len(DEFAULT_POSITIONS) * per_position


class CoilAxes(StepKind):
    name = "coil_axes"
    summary = "coil constants and axis angles to arcseconds: the reference turned on a fixture"
    asks_operator = True
    result_values = ("constants_sigma_ppm.*", "skew_arcsec.*", "skew_sigma_arcsec.*",
                     "chi2_per_dof")  # fmt: skip
    params: ClassVar[dict[str, StepParam]] = {
        "amplitude_a": StepParam("float", 1.0, 0.01, 100.0),
        "samples": StepParam("int", 20, 2, 10000),
        "fixture_sigma_arcsec": StepParam("float", 30.0, 0.1, 3600.0),
    }

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return coil_axes_duration_s(step, timing)

    def peak_coil_current_a(self, step: Step) -> float | None:
        return float(step.params["amplitude_a"])

    def execution(self, ctx: Any, step: Any) -> StepExecution:
        return TurnedReference(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        found = CoilAxesResult.from_dict(result) if isinstance(result, Mapping) else None
        if found is None:
            return []
        consts = ", ".join(f"{ax} {v:.5f} uT/A +- {found.constants_sigma_ppm[ax]:.0f} ppm"
                           for ax, v in found.constants_ut_per_a.items())  # fmt: skip
        skews = ", ".join(f"{p} {v:+.1f} +- {found.skew_sigma_arcsec[p]:.1f} arcsec"
                          for p, v in found.skew_arcsec.items())  # fmt: skip
        return [f"Coil axes '{name}': constants {consts}; axes off square {skews}"
                f" (chi-square per dof {found.chi2_per_dof:.2f})", *found.notes]  # fmt: skip


def position_prompt(index: int, count: int, position: str) -> str:
    """What the operator is asked before each fixture position (the base one first)."""
    what = ("the base position (its axes along the cage's)" if index == 0
            else f"'{position}' from the base position")  # fmt: skip
    return (
        f"Fixture position {index + 1} of {count}: turn the reference on its fixture to"
        f" {what}, keep it still, then confirm"
    )


class TurnedReference(StepExecution):
    def run(self, payload: dict[str, Any]) -> None:
        from rig.cage import coil_axes as method
        from rig.cage.characterize import TRANSIENT_S

        ctx, controller = self.ctx, self.ctx.controller
        if controller.reference_to_cage is None:
            raise RigError(
                f"step '{self.step.name}': the vector method takes its scale from the reference's"
                " certificate: give its correction_matrix in the rig configuration"
            )
        correction, _ = controller.reference_to_cage
        cage = ctx.cfg.cage if ctx.cfg is not None else None
        reference = ctx.cfg.devices.get(cage.reference or "") if cage is not None else None
        certificate = reference.params if reference is not None else {}
        prior = method.SensorPrior(
            method.lower_triangular_part(np.linalg.inv(np.asarray(correction, float))),
            scale_sigma=float(certificate.get("correction_scale_sigma", 5e-5)),
            skew_sigma_rad=float(certificate.get("correction_angle_sigma_arcsec", 20.0))
            / method.ARCSEC_PER_RAD,
            fixture_sigma_rad=payload["fixture_sigma_arcsec"] / method.ARCSEC_PER_RAD,
        )
        data = []
        positions = method.DEFAULT_POSITIONS
        for index, (position, _) in enumerate(positions):
            ask_or_abort(ctx, position_prompt(index, len(positions), position))
            data += method.measure_position(controller, index, payload["amplitude_a"],
                                            payload["samples"], TRANSIENT_S)  # fmt: skip
        fit = method.fit_coil_axes(data, prior)
        result = CoilAxesResult.from_fit(fit).to_dict()
        ctx.record_result(self.step.name, result)
        record_cage_metrology(ctx, self.step.kind, {"result": result})


KIND = CoilAxes()
