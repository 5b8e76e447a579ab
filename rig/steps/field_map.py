"""``field_map``: the cage's field over the DUT's volume, with the reference moved by the operator
over a grid of positions (the homogeneity map, :mod:`rig.cage.homogeneity`)."""

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


@dataclass(frozen=True)
class FieldMapResult:
    """What the field map found: per coil, the largest field error over the mapped volume
    (relative to the coil's field per ampere at the centre, ppm) and the field error per ampere
    where the reference sits during DUT runs (nT/A, rows the field axes, columns the coils), each
    with its 1-sigma; the fit's degree and the scale its residuals put on the readings' sigmas."""

    volume_error_ppm: dict[str, float]
    reference_error_nt_per_a: tuple[tuple[float, ...], ...]
    reference_error_sigma_nt_per_a: tuple[tuple[float, ...], ...]
    degree: float
    noise_scale: dict[str, float]

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping."""
        return {
            "volume_error_ppm": self.volume_error_ppm,
            "reference_error_nt_per_a": [list(r) for r in self.reference_error_nt_per_a],
            "reference_error_sigma_nt_per_a": [
                list(r) for r in self.reference_error_sigma_nt_per_a
            ],
            "degree": self.degree, "noise_scale": self.noise_scale,
        }  # fmt: skip

    @classmethod
    def from_dict(cls, d: Any) -> FieldMapResult:
        """Read a stored result; a :class:`~rig.errors.StoredResultError` names what is wrong."""
        what = "field map result"
        d = stored.mapping(d, what)
        return cls(
            stored.number_map(d, "volume_error_ppm", what),
            stored.matrix3(d, "reference_error_nt_per_a", what),
            stored.matrix3(d, "reference_error_sigma_nt_per_a", what),
            stored.number(d, "degree", what), stored.number_map(d, "noise_scale", what),
        )  # fmt: skip


def _positions(step: Step) -> Any:
    from rig.cage.homogeneity import grid_positions

    return grid_positions(float(step.params["half_width_m"]), int(step.params["points_per_axis"]))


class FieldMap(StepKind):
    name = "field_map"
    summary = "the field over the DUT's volume: the reference moved over a grid by the operator"
    asks_operator = True
    result_values = ("volume_error_ppm.*", "noise_scale.*")
    params: ClassVar[dict[str, StepParam]] = {
        "half_width_m": StepParam("float", 0.1, 0.01, 0.5),
        "points_per_axis": StepParam("int", 3, 3, 5),
        "degree": StepParam("int", 6, 2, 8),
        "reference_m": StepParam("vec3", [0.0, 0.0, -0.08]),
        "amplitude_a": StepParam("float", 1.0, 0.01, 100.0),
        "samples": StepParam("int", 10, 2, 10000),
    }

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        from rig.steps.coil_axes import coil_axes_duration_s

        per_position = coil_axes_duration_s(step, timing) / 4  # the same readings per position
        return len(_positions(step)) * per_position

    def peak_coil_current_a(self, step: Step) -> float | None:
        return float(step.params["amplitude_a"])

    def execution(self, ctx: Any, step: Any) -> StepExecution:
        return MoveReference(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        found = FieldMapResult.from_dict(result) if isinstance(result, Mapping) else None
        if found is None:
            return []
        volume = ", ".join(f"{ax} {v:.0f} ppm" for ax, v in found.volume_error_ppm.items())
        ref = np.array(found.reference_error_nt_per_a)
        sig = np.array(found.reference_error_sigma_nt_per_a)
        at_ref = ", ".join(f"coil {AXES[j]} {np.linalg.norm(ref[:, j]):.2f} +- {sig[:, j].max():.2f}"
                           for j in range(3))  # fmt: skip
        return [f"Field map '{name}': largest error over the volume {volume}; at the reference's"
                f" place {at_ref} nT/A (degree {found.degree:.0f})"]  # fmt: skip


def position_prompt(index: int, count: int, where_m: Any) -> str:
    """What the operator is asked before each grid position."""
    x, y, z = (100.0 * float(v) for v in where_m)
    return (
        f"Field map position {index + 1} of {count}: move the reference to x {x:+.1f} cm,"
        f" y {y:+.1f} cm, z {z:+.1f} cm from the centre, axes along the cage's, then confirm"
    )


class MoveReference(StepExecution):
    def run(self, payload: dict[str, Any]) -> None:
        from rig.cage import homogeneity
        from rig.cage.characterize import TRANSIENT_S
        from rig.cage.coil_axes import measure_position

        ctx, controller = self.ctx, self.ctx.controller
        if controller.reference_to_cage is None:
            raise RigError(f"step '{self.step.name}': the field map reads the reference in the"
                           " cage frame: give its correction_matrix in the rig configuration")  # fmt: skip
        correction, _ = controller.reference_to_cage
        positions = _positions(self.step)
        fields = np.zeros((3, len(positions), 3))
        sigmas = np.zeros((3, len(positions), 3))
        for index, where_m in enumerate(positions):
            ask_or_abort(ctx, position_prompt(index, len(positions), where_m))
            for r in measure_position(controller, index, payload["amplitude_a"],
                                      payload["samples"], TRANSIENT_S):  # fmt: skip
                fields[r.coil, index] = correction @ r.per_amp_ut
                sigmas[r.coil, index] = np.sqrt((correction**2) @ r.sigma_ut**2)
        result, maps = _result(homogeneity, positions, fields, sigmas, payload)
        ctx.record_result(self.step.name, result)
        record_cage_metrology(ctx, self.step.kind, {"result": result, "maps": maps})


def _result(homogeneity: Any, positions: Any, fields: Any, sigmas: Any,
            payload: dict[str, Any]) -> tuple[dict[str, Any], list[dict[str, Any]]]:  # fmt: skip
    """The step's result and, per coil, the map the cage calibration record keeps (degree,
    coefficients and covariance of :class:`rig.cage.homogeneity.FieldMap`, uT/A)."""
    degree = int(payload["degree"])
    volume, ref, ref_sigma, scales = {}, np.zeros((3, 3)), np.zeros((3, 3)), {}
    maps = []
    for coil in range(3):
        fitted = homogeneity.fit_field_map(positions, fields[coil], sigmas[coil], degree)
        maps.append({"degree": degree, "coefficients": fitted.coefficients.tolist(),
                     "covariance": fitted.covariance.tolist()})  # fmt: skip
        centre, _ = fitted.field_ut(np.zeros((1, 3)))
        errors, _ = fitted.error_ut(positions)
        volume[AXES[coil]] = float(1e6 * np.abs(errors).max() / np.linalg.norm(centre))
        value, sigma = fitted.error_ut(np.asarray(payload["reference_m"], float))
        ref[:, coil], ref_sigma[:, coil] = 1000.0 * value[0], 1000.0 * sigma[0]
        scales[AXES[coil]] = fitted.noise_scale
    found = FieldMapResult(volume, tuple(map(tuple, ref.tolist())),
                           tuple(map(tuple, ref_sigma.tolist())), float(degree), scales)  # fmt: skip
    return found.to_dict(), maps


KIND = FieldMap()
