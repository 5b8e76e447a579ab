"""``rig calibrate``: refuse field magnitudes no calibration uses (a unit slip), naming both
readings of the number (ADR 0025's companion check; the arithmetic is in rig.io.field_units)."""

from __future__ import annotations

import argparse
from typing import Any

from rig.errors import UserInputError
from rig.io.field_units import implausible_field, is_counts, ut_per


def check_plausible_fields(samples: Any, args: argparse.Namespace) -> None:
    """Raise a one-line UserInputError when the reference's or the readings' median magnitude is
    outside any plausible calibration field in the units given, or when the two differ by a
    factor no sensor scale has; ``--allow-implausible-field`` keeps them."""
    import numpy as np

    if args.allow_implausible_field:
        return
    field_unit = args.field_unit or ("uT" if is_counts(args.unit) else args.unit)
    reference_ut = float(np.median(samples.field_magnitude_ut))
    readings_ut = float(np.median(np.linalg.norm(samples.measured_ut, axis=1)))
    readings = f"the readings (median |m| in --unit {args.unit})"
    readings_wrong = implausible_field(
        readings, readings_ut / ut_per(args.unit), args.unit, "--unit"
    )
    if args.field_magnitude is not None and args.field_magnitude not in (args.columns or []):
        try:
            what = f"--field-magnitude {float(args.field_magnitude):g}"
        except ValueError:
            what = f"the reference column {args.field_magnitude} (median)"
    elif args.field is not None:
        what = "the reference field (median |h| of --field)"
    else:
        what = "the reference field"
    flag = "--unit" if readings_wrong and args.field_unit is None else "--field-unit"
    message = implausible_field(what, reference_ut / ut_per(field_unit), field_unit, flag)
    message = message or readings_wrong
    message = message or implausible_field(readings, readings_ut / ut_per(args.unit), args.unit,
                                           "--unit", other_ut=reference_ut)  # fmt: skip
    if message:
        raise UserInputError(message)
