"""The closed loop's per-tick record: written by the loop (CSV, one row per tick), read back for
the report's plot."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

import numpy as np

from rig.hil.loop import Tick
from rig.steps.base import Array
from rig.store import safe_files

MAX_TICKS_BYTES = 200_000_000
"""The largest per-tick record the report reads (bytes)."""


def read_ticks(folder: Path, name: Any) -> dict[str, Array] | None:
    """A per-tick record of the run folder (a file name, never a path elsewhere): ``t_s``,
    ``rate_deg_s`` (magnitude) and ``dipole_am2`` (magnitude); None when missing or unreadable."""
    if not isinstance(name, str) or "/" in name or "\\" in name or name.startswith("."):
        return None
    try:
        text = safe_files.read_text(folder / name, MAX_TICKS_BYTES)
        rows = list(csv.DictReader(io.StringIO(text, newline="")))
        col = {k: np.array([float(r[k]) for r in rows]) for k in rows[0]} if rows else None
    except (OSError, ValueError, KeyError, safe_files.UnsafeFileError):
        return None
    if col is None:
        return None
    rate = np.linalg.norm([col[f"rate_{a}_deg_s"] for a in "xyz"], axis=0)
    dipole = np.linalg.norm([col[f"dipole_{a}_am2"] for a in "xyz"], axis=0)
    return {"t_s": col["t_s"], "rate_deg_s": rate, "dipole_am2": dipole}


def write_ticks(path: Path, ticks: list[Tick], latency_s: list[float],
                rod_a: list[Array]) -> None:  # fmt: skip
    """The per-tick record (CSV): time, attitude, rate, field, reading, dipole, latency, rods."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "mrp_1", "mrp_2", "mrp_3", "rate_x_deg_s", "rate_y_deg_s",
                    "rate_z_deg_s", "field_x_ut", "field_y_ut", "field_z_ut", "reading_x_ut",
                    "reading_y_ut", "reading_z_ut", "dipole_x_am2", "dipole_y_am2",
                    "dipole_z_am2", "latency_ms", "rod_x_a", "rod_y_a", "rod_z_a"])  # fmt: skip
        for tick, lat, rods in zip(ticks, latency_s, rod_a, strict=True):
            reading = tick.reading_ut if tick.reading_ut is not None else np.full(3, math.nan)
            row = [tick.t_s, *tick.mrp, *tick.rate_deg_s, *tick.field_ut, *reading,
                   *tick.dipole_am2, lat * 1000.0, *rods]  # fmt: skip
            w.writerow(f"{v:.9g}" for v in row)
