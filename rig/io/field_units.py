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


EARTH_FIELD_UT = (20.0, 70.0)
"""Range of the Earth's field magnitude at the surface (uT)."""
PLAUSIBLE_FIELD_UT = (2.0, 1000.0)
"""Field magnitudes (uT) a magnetometer calibration can plausibly use: from a weak cage setting to
10 G (beyond any calibration cage, and where common magnetometers saturate: 800 uT to 8 G)."""
SCALE_RATIO_LIMIT = 5.0
"""Readings and reference whose typical magnitudes differ by more than this factor imply a
scale no sensor has (a unit slip in one of them); ArduPilot too refuses a scale outside 0.2-5."""
IMPLAUSIBLE_OVERRIDE = "--allow-implausible-field"


def _in_unit(value_ut: float) -> str:
    """``value_ut`` read in the unit that makes it an Earth-like field: '47 uT' for 4700."""
    for unit in ("uT", "G", "mG", "nT", "mT", "T"):
        if PLAUSIBLE_FIELD_UT[0] <= value_ut * UT_PER_UNIT[unit] <= PLAUSIBLE_FIELD_UT[1]:
            return f"{value_ut:.4g} {unit}"
    return ""


def _reading(value: float, unit: str) -> str:
    """'47 G is 4700 uT, 67 times the strongest Earth field (70 uT)' and the like."""
    ut = value * ut_per(unit)
    lo, hi = EARTH_FIELD_UT
    if ut > hi:
        where = f"{ut / hi:.3g} times the strongest Earth field ({hi:g} uT)"
    else:
        where = f"1/{lo / ut:.3g} of the weakest Earth field ({lo:g} uT)"
    if unit == "uT":
        return f"{value:.4g} uT is {where}"
    shown = unit if not is_counts(unit) else f"counts at {unit} per uT"
    return f"{value:.4g} {shown} is {ut:.4g} uT, {where}"


def implausible_field(
    what: str, value: float, unit: str, flag: str, other_ut: float | None = None
) -> str | None:
    """Why a typical field magnitude ``value`` (in ``unit``) is implausible, naming both readings
    of the number and what to pass, or None when it is plausible. ``what``: the input named
    ('--field-magnitude', 'the reference column', 'the readings'); ``flag``: the option that sets
    its unit; ``other_ut``: the other side's magnitude (uT), for the ratio check."""
    ut = value * ut_per(unit)
    lo, hi = PLAUSIBLE_FIELD_UT
    ratio = 1.0 if other_ut is None else max(ut / other_ut, other_ut / ut)
    if lo <= ut <= hi and ratio <= SCALE_RATIO_LIMIT:
        return None
    meant = _in_unit(value)
    guess = (
        f"; did you mean {meant}? pass {flag} {meant.split()[-1]}" if meant else f"; check {flag}"
    )
    if lo <= ut <= hi:
        assert other_ut is not None
        return (
            f"{what}: {value:.4g} {unit} is {ut:.4g} uT, against {other_ut:.4g} uT on the other side"
            f" of the fit: a scale of {ut / other_ut:.3g}, which no sensor has: check --unit and"
            f" --field-unit, or pass {IMPLAUSIBLE_OVERRIDE} to keep it"
        )
    return (
        f"{what}: {_reading(value, unit)}, outside any calibration field ({lo:g}-{hi:g} uT)"
        f"{guess}, or {IMPLAUSIBLE_OVERRIDE} to keep it"
    )
