"""``coil_scalar``: the coil constants and the angles between the coil axes from a total-field
magnetometer at the cage centre (the scalar method, :mod:`rig.cage.coil_scalar`): no certificate,
no fixture, no operator."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

import timebase
from rig.errors import RigError
from rig.steps.base import StepExecution, StepKind, record_cage_metrology
from rig.steps.coil_axes import AXES, PAIRS
from rig.steps.vocabulary import RigTiming, Step, StepParam

CURRENT_STEP_A = 1e-3
"""Currents are rounded to 1 mA, a value every coil supply sets exactly (0.1 or 1 mA steps)."""
SCALAR_RATE_HZ = 10.0
GOOD_SHARE = 0.5
"""A point with fewer valid readings than this share is left out (the sensor lost its signal)."""


def design(directions: int, shells_ut: list[float], axis: np.ndarray | None,
           dead_zone_deg: float, seed: int = 0) -> list[np.ndarray]:  # fmt: skip
    """The total fields to set (uT, cage frame): ``directions`` spread over the sphere, those in
    the sensor's dead zones left out, on each shell, all in a random order (seeded): the lab
    field's drift over the sweep then falls on the directions and magnitudes alike, as noise the
    fit sees between points, instead of a pattern it would take for the coils."""
    from rig.cage.coil_scalar import outside_dead_zones
    from rig.steps.geometry import fibonacci_directions

    units = outside_dead_zones(fibonacci_directions(directions), axis, dead_zone_deg)
    fields = [shell * u for shell in shells_ut for u in units]
    order = np.random.default_rng(seed).permutation(len(fields))
    return [fields[i] for i in order]


def coil_scalar_duration_s(step: Step, timing: RigTiming) -> float:
    """Cage time of the step (s): per point a ramp of about a second within the slew limit (a
    coil's polarity flip included), the settling and the readings (one more than asked: the one in
    flight when the flush came is left out)."""
    points = int(step.params["directions"]) * len(step.params["field_ut"])
    per_point = (
        1.0 + float(step.params["settle_s"]) + (int(step.params["samples"]) + 2) / SCALAR_RATE_HZ
    )
    return points * per_point


class CoilScalar(StepKind):
    name = "coil_scalar"
    summary = "coil constants and axis angles from a total-field magnetometer (no certificate)"
    result_values = ("constants_sigma_ppm.*", "skew_arcsec.*", "skew_sigma_arcsec.*",
                     "chi2_per_dof", "points")  # fmt: skip
    params: ClassVar[dict[str, StepParam]] = {
        "field_ut": StepParam("list_float", [22.0, 45.0], 17.0, 1000.0),
        "directions": StepParam("int", 30, 8, 500),
        "samples": StepParam("int", 10, 2, 1000),
        "settle_s": StepParam("float", 0.5, 0.0, 60.0),
    }

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return coil_scalar_duration_s(step, timing)

    def execution(self, ctx: Any, step: Any) -> StepExecution:
        return ScalarSweep(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        if not isinstance(result, Mapping) or "constants_ut_per_a" not in result:
            return []
        consts = ", ".join(f"{ax} {v:.5f} uT/A +- {result['constants_sigma_ppm'][ax]:.1f} ppm"
                           for ax, v in result["constants_ut_per_a"].items())  # fmt: skip
        skews = ", ".join(f"{p} {v:+.1f} +- {result['skew_sigma_arcsec'][p]:.1f} arcsec"
                          for p, v in result["skew_arcsec"].items())  # fmt: skip
        return [f"Coil constants by the scalar method '{name}' ({result['points']} points):"
                f" {consts}; axes off square {skews} (chi-square per dof"
                f" {result['chi2_per_dof']:.2f})", *result.get("notes", [])]  # fmt: skip


class ScalarSweep(StepExecution):
    def run(self, payload: dict[str, Any]) -> None:
        from rig.cage.coil_scalar import fit_scalar_coils

        ctx, controller = self.ctx, self.ctx.controller
        cage = ctx.cfg.cage if ctx.cfg is not None else None
        if cage is None or cage.scalar is None:
            raise RigError(f"step '{self.step.name}': the scalar method needs a total-field"
                           " magnetometer: name it in the rig configuration ([cage] scalar)")  # fmt: skip
        shells = [float(v) for v in payload["field_ut"]]
        if not shells or any(not 17.0 <= v <= cage.max_field_ut for v in shells):
            raise RigError(f"step '{self.step.name}': field_ut must list total fields of 17 uT"
                           f" (a scalar sensor's lower limit) to {cage.max_field_ut:g} uT")  # fmt: skip
        device = ctx.cfg.devices[cage.scalar]
        axis = device.params.get("optical_axis")
        fields = design(int(payload["directions"]), shells,
                        None if axis is None else np.array(axis, float),
                        float(device.params.get("dead_zone_deg", 15.0)))  # fmt: skip
        sensor = ctx.scalar_magnetometer(cage.scalar)
        sensor.set_cycle(float(device.params.get("rate_hz", SCALAR_RATE_HZ)))
        try:
            readings, lost, beyond = self._sweep(sensor, fields, int(payload["samples"]),
                                                 float(payload["settle_s"]))  # fmt: skip
        finally:
            controller.set_currents(np.zeros(3))
        fit = fit_scalar_coils(readings, controller.model.k_ut_per_a,
                               float(device.params.get("offset_sigma_nt", 3.0)))  # fmt: skip
        result = _result(fit, readings, lost, beyond)
        ctx.record_result(self.step.name, result)
        record_cage_metrology(ctx, self.step.kind, {"result": result})

    def _sweep(self, sensor: Any, fields: list[np.ndarray], samples: int, settle_s: float
               ) -> tuple[list[Any], int, int]:  # fmt: skip
        """Set each total field, read the sensor: the readings, how many points had no signal and
        how many needed more than the current limit."""
        from rig.cage.coil_scalar import ScalarReading

        controller = self.ctx.controller
        start, readings, lost, beyond = timebase.monotonic(), [], 0, 0
        for field_ut in fields:
            controller.limits.check_field(field_ut, f"step '{self.step.name}'")
            target = (
                np.round(controller.model.currents_a(field_ut) / CURRENT_STEP_A) * CURRENT_STEP_A
            )
            if np.any(np.abs(target) > np.array(controller.limits.max_current_a)):
                beyond += 1  # the lab field added: more current than the coils may carry
                continue
            currents = controller.set_currents(target)
            controller.sleep(settle_s)
            sensor.flush()
            sensor.read_total_nt()  # its cycle may have begun before the flush
            values = [sensor.read_total_nt() for _ in range(samples)]
            good = np.array([v for v in values if v is not None], float) * 1e-3
            if len(good) < max(2, GOOD_SHARE * samples):
                lost += 1
                continue
            readings.append(ScalarReading(currents, timebase.monotonic() - start, float(good.mean()),
                                          float(good.std(ddof=1) / np.sqrt(len(good)))))  # fmt: skip
        if lost:
            self.ctx.event("warning", f"{self.step.name}: {lost} of {len(fields)} points had no"
                           " signal from the scalar sensor (a dead zone or a field out of range)")  # fmt: skip
        if beyond:
            self.ctx.event("warning", f"{self.step.name}: {beyond} of {len(fields)} points would"
                           " need more than the coils' current limit (the lab field added); left"
                           " out")  # fmt: skip
        return readings, lost, beyond


def _result(fit: Any, readings: list[Any], lost: int, beyond: int) -> dict[str, Any]:
    """The stored result: constants, skews, the lab field, the sensor's offset and the readings."""
    return {
        "constants_ut_per_a": dict(zip(AXES, map(float, fit.constants_ut_per_a), strict=True)),
        "constants_sigma_ppm": dict(zip(AXES, map(float, 1e6 * fit.constants_sigma
                                                  / fit.constants_ut_per_a), strict=True)),
        "skew_arcsec": dict(zip(PAIRS, map(float, fit.skew_arcsec), strict=True)),
        "skew_sigma_arcsec": dict(zip(PAIRS, map(float, fit.skew_sigma_arcsec), strict=True)),
        "k_ut_per_a_upper": fit.k_ut_per_a.tolist(),
        "lab_field_ut": fit.lab_field_ut.tolist(),
        "drift_nt_per_min": fit.drift_nt_per_min.tolist(),
        "sensor_offset_nt": fit.offset_nt, "sensor_offset_sigma_nt": fit.offset_sigma_nt,
        "chi2_per_dof": fit.chi2 / max(fit.dof, 1), "between_points_nt": fit.between_nt,
        "points": len(readings), "points_lost": lost,
        "points_beyond_limits": beyond,
        "residual_rms_nt": float(np.sqrt(np.mean(fit.residuals_nt**2))),
        "readings": [{"currents_a": r.currents_a.tolist(), "t_s": r.t_s, "total_ut": r.total_ut,
                      "sigma_ut": r.sigma_ut} for r in readings],
        "notes": list(fit.notes),
    }  # fmt: skip


KIND = CoilScalar()
