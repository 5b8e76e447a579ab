"""The DUT's readings and the reference field in the DUT's own axes, as the steps that compare
them axis by axis take them (cross_field, frequency_response): the readings corrected by the
run's latest vector calibration, the reference field turned by its mounting rotation."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from rig.analysis import apply_correction_unloaded
from rig.calibration.params import rotation_from_vector
from rig.calibration.record import latest_calibration
from rig.steps.base import Array


@dataclass(frozen=True)
class InSensorAxes:
    """The reference field (uT, (N, 3)) and the DUT's readings, and the calibration that turned
    them into the sensor's axes with its mounting (deg); None: both as they came (cage axes,
    raw readings)."""

    field_ut: Array
    readings_ut: Array
    calibration: str | None
    mounting_deg: tuple[float, ...] | None


def in_sensor_axes(results: Mapping[str, Any], field_ut: Array, readings_ut: Array) -> InSensorAxes:
    """``field_ut`` (cage frame) and ``readings_ut`` in the sensor's axes when ``results`` hold a
    vector calibration with a mounting, else unchanged."""
    latest = latest_calibration(results, "vector")
    mounting = latest[1].mounting_deg if latest is not None else None
    if latest is None or mounting is None:
        return InSensorAxes(field_ut, readings_ut, None, None)
    rot = rotation_from_vector(np.radians(np.asarray(mounting, float)))
    corrected = apply_correction_unloaded(latest[1].correction, readings_ut)
    return InSensorAxes(field_ut @ rot.T, corrected @ rot.T, latest[0],
                        tuple(float(v) for v in mounting))  # fmt: skip
