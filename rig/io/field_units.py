"""Units of magnetic-field columns in a file, converted to uT (the unit of every computation and
result, ADR 0002) where the file is read."""

from __future__ import annotations

import math

UT_PER_UNIT: dict[str, float] = {"T": 1e6, "mT": 1e3, "uT": 1.0, "nT": 1e-3, "G": 100.0, "mG": 0.1}
"""Microtesla per unit of each field unit a file may use (1 G = 100 uT)."""

UNIT_HELP = f"{', '.join(UT_PER_UNIT)}, or a number: counts per uT"


def ut_per(unit: str) -> float:
    """uT per unit of ``unit``: a name of :data:`UT_PER_UNIT` (case matters: mG is not MG), or a positive number of counts per
    uT (a raw sensor's LSB scale, e.g. 75 for a PNI RM3100 at cycle count 200). ValueError with
    the choices otherwise."""
    if unit in UT_PER_UNIT:
        return UT_PER_UNIT[unit]
    try:
        counts_per_ut = float(unit)
    except ValueError:
        raise ValueError(f"unknown field unit '{unit}': use {UNIT_HELP}") from None
    if not (math.isfinite(counts_per_ut) and counts_per_ut > 0):
        raise ValueError(f"counts per uT must be a positive number, got '{unit}'")
    return 1.0 / counts_per_ut


def is_counts(unit: str) -> bool:
    """The unit is a counts-per-uT factor, not a field unit."""
    try:
        ut_per(unit)
    except ValueError:
        return False
    return unit not in UT_PER_UNIT
