"""``orbit_replay``: the field an orbiting spacecraft sees (sgp4 from a TLE, IGRF, an attitude),
tracked set-point by set-point at ``rate_hz``, with solar-panel currents on the loads."""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from rig.steps.base import FieldStepKind, load_commands
from rig.steps.vocabulary import (
    MAX_FIELD_SETPOINTS_PER_STEP,
    Command,
    EndCommand,
    FieldCommand,
    LoadCommand,
    LoadPayload,
    ProcedureError,
    RigTiming,
    Step,
    StepParam,
)


class OrbitReplay(FieldStepKind):
    name = "orbit_replay"
    summary = "replay an orbit's field (TLE + IGRF) with panel currents"
    hold_from_field = False  # the replay keeps its schedule; a late set-point is not waited for
    params: ClassVar[dict[str, StepParam]] = {
        "tle": StepParam("list_str", required=True),
        "start": StepParam("str", required=True),
        "duration_s": StepParam("float", required=True, minimum=0.1, maximum=86400.0),
        "time_scale": StepParam("float", 1.0, 0.01, 10000.0),
        "rate_hz": StepParam("float", 10.0, 0.1, 200.0),
        "attitude": StepParam("str", "nadir", choices=("inertial", "nadir", "tumbling")),
        "tumble_deg_s": StepParam("float", 2.0, 0.0, 360.0),
        "panels": StepParam("list_dict", []),
        "field_scale": StepParam("float", 1.0, 0.05, 1.0),
    }
    """``field_scale``: the fraction of the orbit's field replayed (1 = as in orbit): a cage whose
    limits the full field would reach, with the ambient field to cancel, replays it scaled; the
    field's direction and the panels' currents are unchanged."""

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        from rig.steps.orbit import FACES, validate_orbit

        problem = validate_orbit(params, where, MAX_FIELD_SETPOINTS_PER_STEP)
        if problem is not None:
            raise ProcedureError(problem)
        for panel in params["panels"]:
            ch, face, max_a = panel.get("channel"), panel.get("face"), panel.get("max_a")
            if ch not in loads or face not in FACES or not isinstance(max_a, int | float):
                raise ProcedureError(
                    f"{where}: a panel needs channel (one of the procedure's loads), face ({', '.join(FACES)}) and max_a"
                )

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return float(step.params["duration_s"])

    def compile(self, step: Step, base: Path, timing: RigTiming) -> tuple[list[Command], float]:
        """Field commands at ``rate_hz`` (tracked, no ramps), the panels' currents (1 mA
        resolution, sent when they change by 2 mA or go to zero) and any load profiles."""
        from rig.steps.orbit import orbit_track, panel_current, parse_start

        p = step.params
        t_wall = np.arange(0.0, p["duration_s"], 1.0 / p["rate_hz"])
        try:
            track = orbit_track(p["tle"][0], p["tle"][1], parse_start(p["start"]),
                                t_wall * p["time_scale"], p["attitude"], p["tumble_deg_s"])  # fmt: skip
        except ValueError as exc:
            raise ProcedureError(
                f"{step.where}: step {step.index + 1} (orbit_replay): {exc}"
            ) from None
        field_ut = track.field_body_ut * float(p["field_scale"])
        cmds: list[Command] = [FieldCommand(float(t), {"field_ut": [float(v) for v in f], "track": True})
                for t, f in zip(t_wall, field_ut, strict=True)]  # fmt: skip
        duration = float(p["duration_s"])
        for panel in p["panels"]:
            ch = panel["channel"]
            amps = np.round(panel_current(track, panel["face"], float(panel["max_a"])), 3)
            last = None
            # eclipse entry and exit are steps; in between the current follows the sun angle
            jumps = np.r_[True, track.sunlit[1:] != track.sunlit[:-1]]
            for t, a, jump in zip(t_wall, amps, jumps, strict=True):
                if last is None or abs(a - last) >= 0.002 or (a == 0.0 and last != 0.0):
                    payload: LoadPayload = {"channel": ch, "current_a": float(a)}
                    if last is not None and not jump:
                        payload["track"] = True  # followed, not a step to settle after
                    cmds.append(LoadCommand(float(t), payload))
                    last = a
            cmds.append(LoadCommand(duration, {"channel": ch, "current_a": 0.0}))
        cmds += load_commands(step, duration, base)
        cmds.append(EndCommand(duration))
        return cmds, duration


KIND = OrbitReplay()
