"""Load-current profiles of a field step (``loads:`` in a procedure): their parameters and the
set-points they make."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from rig.steps.vocabulary import Param, ProcedureError

LOAD_PROFILES: dict[str, dict[str, Param]] = {
    "constant": {"current_a": Param("float", required=True, minimum=-1000.0, maximum=1000.0)},
    "steps": {
        "levels_a": Param("list_float", required=True),
        "dwell_s": Param("float", required=True, minimum=0.05),
    },
    "square": {
        "low_a": Param("float", 0.0),
        "high_a": Param("float", required=True),
        "period_s": Param("float", required=True, minimum=0.1),
        "duty": Param("float", 0.5, 0.01, 0.99),
    },
    "ramp": {
        "from_a": Param("float", 0.0),
        "to_a": Param("float", required=True),
        "step_s": Param("float", 0.1, 0.02),
    },
    "beacon": {
        "base_a": Param("float", 0.0),
        "pulse_a": Param("float", required=True),
        "period_s": Param("float", 20.0, 0.1),
        "width_s": Param("float", 2.0, 0.01),
    },
    "csv": {"file": Param("str", required=True), "column": Param("str", required=True)},
}


def load_profile(
    kind: str, p: dict[str, Any], duration_s: float, base: Path
) -> list[tuple[float, float]]:
    """(time offset, current A) set-points of a load profile over ``duration_s``."""
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
        path = (base / p["file"]) if not Path(p["file"]).is_absolute() else Path(p["file"])
        try:
            with path.open(newline="") as fh:
                rows = list(csv.DictReader(fh))
            return [
                (float(r["t_s"]), float(r[p["column"]]))
                for r in rows
                if float(r["t_s"]) < duration_s
            ]
        except FileNotFoundError:
            raise ProcedureError(f"load profile file {path} not found") from None
        except (KeyError, ValueError) as exc:
            raise ProcedureError(
                f"{path}: needs numeric columns 't_s' and '{p['column']}' ({exc})"
            ) from None
    raise AssertionError(kind)
