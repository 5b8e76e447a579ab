"""Load-current profiles of a field step (``loads:`` in a procedure): their parameters and the
set-points they make.

A ``csv`` profile's file must lie in the procedure's folder (:func:`inside_folder`) and is bounded
by :data:`MAX_CSV_PROFILE_BYTES` and :data:`MAX_CSV_PROFILE_ROWS`; every profile by
:data:`MAX_LOAD_SETPOINTS_PER_STEP`.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

from rig.steps.vocabulary import (
    MAX_CSV_PROFILE_BYTES,
    MAX_CSV_PROFILE_ROWS,
    MAX_LOAD_SETPOINTS_PER_STEP,
    NOT_FINITE_FIX,
    NotFiniteError,
    ProcedureError,
    StepParam,
    finite_number,
    inside_folder,
)

LOAD_PROFILES: dict[str, dict[str, StepParam]] = {
    "constant": {"current_a": StepParam("float", required=True, minimum=-1000.0, maximum=1000.0)},
    "steps": {
        "levels_a": StepParam("list_float", required=True),
        "dwell_s": StepParam("float", required=True, minimum=0.05),
    },
    "square": {
        "low_a": StepParam("float", 0.0),
        "high_a": StepParam("float", required=True),
        "period_s": StepParam("float", required=True, minimum=0.1),
        "duty": StepParam("float", 0.5, 0.01, 0.99),
    },
    "ramp": {
        "from_a": StepParam("float", 0.0),
        "to_a": StepParam("float", required=True),
        "step_s": StepParam("float", 0.1, 0.02),
    },
    "beacon": {
        "base_a": StepParam("float", 0.0),
        "pulse_a": StepParam("float", required=True),
        "period_s": StepParam("float", 20.0, 0.1),
        "width_s": StepParam("float", 2.0, 0.01),
    },
    "csv": {
        "file": StepParam("str", required=True, text="path"),
        "column": StepParam("str", required=True),
    },
}


def profile_setpoints(kind: str, p: dict[str, Any], duration_s: float, base: Path) -> int:
    """How many set-points (at most) the profile makes over ``duration_s``, without making them; a
    ``csv`` profile's file is read and checked (:func:`read_csv_profile`)."""
    if kind == "constant":
        return 1
    if kind == "steps":
        return max(1, math.ceil(duration_s / float(p["dwell_s"])))
    if kind == "square":
        return 2 * math.ceil(duration_s / float(p["period_s"]))
    if kind == "ramp":
        return max(1, int(duration_s / float(p["step_s"])))
    if kind == "beacon":
        return 1 + 2 * math.ceil(duration_s / float(p["period_s"]))
    if kind == "csv":
        return sum(1 for t, _ in read_csv_profile(p, base) if t < duration_s)
    raise AssertionError(kind)


def read_csv_profile(p: dict[str, Any], base: Path) -> list[tuple[float, float]]:
    """(t_s, current A) rows of a ``csv`` profile: ``p["file"]`` inside the folder ``base`` (the
    procedure's), at most :data:`MAX_CSV_PROFILE_BYTES` and :data:`MAX_CSV_PROFILE_ROWS`, numeric
    and finite ``t_s`` (>= 0) and ``p["column"]``. Errors name the file, line and column."""
    path = inside_folder(base, p["file"])
    column = p["column"]
    try:
        if path.exists() and not path.is_file():  # a folder, a FIFO that would block, a device
            raise ProcedureError(f"load profile file {path}: not a regular file")
        with path.open("rb") as fh:
            data = fh.read(MAX_CSV_PROFILE_BYTES + 1)
    except FileNotFoundError:
        raise ProcedureError(f"load profile file {path} not found") from None
    except OSError as exc:
        raise ProcedureError(f"load profile file {path}: cannot read it ({exc.strerror})") from None
    if len(data) > MAX_CSV_PROFILE_BYTES:
        raise ProcedureError(
            f"{path}: a CSV load profile may have at most {MAX_CSV_PROFILE_BYTES} bytes"
            " (MAX_CSV_PROFILE_BYTES): shorten it or lower its rate"
        )
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ProcedureError(f"{path}: not UTF-8 text (byte {exc.start}): save it as CSV") from None
    reader = csv.DictReader(io.StringIO(text, newline=""))
    out: list[tuple[float, float]] = []
    try:
        for row in reader:
            line = reader.line_num
            if len(out) >= MAX_CSV_PROFILE_ROWS:
                raise ProcedureError(
                    f"{path}:{line}: a CSV load profile may have at most {MAX_CSV_PROFILE_ROWS}"
                    " rows (MAX_CSV_PROFILE_ROWS): shorten it or lower its rate"
                )
            t = _csv_number(row, "t_s", path, line)
            if t < 0:
                raise ProcedureError(f"{path}:{line}: 't_s' must not be negative, got {t:g}")
            out.append((t, _csv_number(row, column, path, line)))
    except csv.Error as exc:
        raise ProcedureError(f"{path}:{reader.line_num}: not CSV ({exc})") from None
    return out


def _csv_number(row: dict[Any, Any], column: str, path: Path, line: int) -> float:
    cell = row.get(column)
    if not isinstance(cell, str):
        raise ProcedureError(
            f"{path}:{line}: needs numeric columns 't_s' and '{column}' (no '{column}' here)"
        )
    try:
        value = float(cell)
    except ValueError:
        raise ProcedureError(f"{path}:{line}: '{column}' must be a number, got {cell!r}") from None
    if finite_number(value) is None:
        raise NotFiniteError(f"{path}:{line}: '{column}' is {cell.strip()!r}; {NOT_FINITE_FIX}")
    return value


def load_profile(
    kind: str, p: dict[str, Any], duration_s: float, base: Path
) -> list[tuple[float, float]]:
    """(time offset, current A) set-points of a load profile over ``duration_s``; at most
    :data:`MAX_LOAD_SETPOINTS_PER_STEP` (the language checks that first, with the step's line)."""
    if kind != "csv" and profile_setpoints(kind, p, duration_s, base) > MAX_LOAD_SETPOINTS_PER_STEP:
        raise ProcedureError(
            f"a {kind} load profile over {duration_s:g} s makes more than"
            f" {MAX_LOAD_SETPOINTS_PER_STEP} set-points (MAX_LOAD_SETPOINTS_PER_STEP)"
        )
    if kind == "constant":
        return [(0.0, p["current_a"])]
    if kind == "steps":
        levels, dwell = p["levels_a"], p["dwell_s"]
        n = max(1, math.ceil(duration_s / dwell))
        return [(i * dwell, levels[i % len(levels)]) for i in range(n)]
    if kind == "square":
        out: list[tuple[float, float]] = []
        t = 0.0
        while t < duration_s:
            out += [(t, p["high_a"]), (t + p["duty"] * p["period_s"], p["low_a"])]
            t += p["period_s"]
        return [x for x in out if x[0] < duration_s]
    if kind == "ramp":
        n = max(1, int(duration_s / p["step_s"]))
        return [
            (i * p["step_s"], p["from_a"] + (p["to_a"] - p["from_a"]) * i / max(n - 1, 1))
            for i in range(n)
        ]
    if kind == "beacon":
        out = [(0.0, p["base_a"])]
        t = 0.0
        while t < duration_s:
            out += [(t, p["pulse_a"]), (t + p["width_s"], p["base_a"])]
            t += p["period_s"]
        return sorted(x for x in out if x[0] < duration_s)
    if kind == "csv":
        return [(t, amps) for t, amps in read_csv_profile(p, base) if t < duration_s]
    raise AssertionError(kind)
