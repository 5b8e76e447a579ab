"""Compile a procedure into a plan: per step, a timeline of small commands.

A plan is data, so it can be dry-run (:func:`dry_run`): duration, peak currents and fields, and
limit violations are known before any hardware is touched.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from rig.procedure.language import FIELD_STEPS, Procedure, ProcedureError, Step

if TYPE_CHECKING:
    from rig.config import RigConfig

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Command:
    """One thing to do at ``t_s`` seconds after its step starts."""

    t_s: float
    kind: str  # field, load, prompt, calibrate, check, report, trim
    payload: dict[str, Any]


@dataclass(frozen=True)
class StepPlan:
    """A step's commands, time-ordered, and its nominal duration (s)."""

    step: Step
    duration_s: float
    commands: tuple[Command, ...]


def fibonacci_directions(n: int) -> Array:
    """``n`` nearly uniform unit vectors (Fibonacci sphere)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z**2)
    phi = math.pi * (1.0 + math.sqrt(5.0)) * k
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def field_sequence(step: Step) -> list[tuple[float, Array]]:
    """(time offset, field) pairs of a field step."""
    p = step.params
    if step.kind == "null_field":
        return [(0.0, np.zeros(3))]
    if step.kind == "set_field":
        return [(0.0, np.array(p["field_ut"]))]
    if step.kind == "hold":
        return []
    if step.kind in ("sphere_sweep", "live_calibrate"):
        n_dirs = (
            p["directions"] if step.kind == "sphere_sweep" else math.ceil(p["max_s"] / p["dwell_s"])
        )
        dirs = fibonacci_directions(n_dirs)
        rng = np.random.default_rng(p["seed"])
        dirs = dirs[rng.permutation(len(dirs))]
        lo, hi = p["magnitude_ut"]
        mags = np.linspace(lo, hi, len(dirs)) if hi > lo else np.full(len(dirs), lo)
        mags = mags[rng.permutation(len(mags))]
        return [(i * p["dwell_s"], dirs[i] * mags[i]) for i in range(len(dirs))]
    if step.kind == "axis_sweep":
        axis_index = "xyz".index(p["axis"])
        out = []
        for i, v in enumerate(np.linspace(p["from_ut"], p["to_ut"], p["points"])):
            f = np.zeros(3)
            f[axis_index] = v
            out.append((i * p["dwell_s"], f))
        return out
    if step.kind == "rotate":
        spin = np.array(p["axis"], float)
        norm = float(np.linalg.norm(spin))
        if norm == 0:
            raise ProcedureError(
                f"{step.where}: step {step.index + 1} (rotate): axis must not be zero"
            )
        spin /= norm
        helper = np.array([1.0, 0, 0]) if abs(spin[0]) < 0.9 else np.array([0, 1.0, 0])
        u = np.cross(spin, helper)
        u /= np.linalg.norm(u)
        v = np.cross(spin, u)
        angles = np.linspace(0, 2 * math.pi, p["points"], endpoint=False)
        return [
            (i * p["dwell_s"], p["magnitude_ut"] * (math.cos(a) * u + math.sin(a) * v))
            for i, a in enumerate(angles)
        ]
    raise AssertionError(step.kind)


def orbit_commands(step: Step) -> tuple[list[Command], float]:
    """Field commands at ``rate_hz`` (tracked, no ramps) and panel-current commands of an orbit."""
    from rig.procedure.orbit import FACES, orbit_track, panel_current, parse_start

    p = step.params
    where = f"{step.where}: step {step.index + 1} (orbit_replay)"
    if len(p["tle"]) != 2:
        raise ProcedureError(f"{where}: 'tle' must be the two TLE lines")
    try:
        start = parse_start(p["start"])
    except ValueError as exc:
        raise ProcedureError(f"{where}: {exc}") from None
    t_wall = np.arange(0.0, p["duration_s"], 1.0 / p["rate_hz"])
    try:
        track = orbit_track(
            p["tle"][0],
            p["tle"][1],
            start,
            t_wall * p["time_scale"],
            p["attitude"],
            p["tumble_deg_s"],
        )
    except ValueError as exc:
        raise ProcedureError(f"{where}: {exc}") from None
    cmds = [Command(float(t), "field", {"field_ut": [float(v) for v in f], "track": True})
            for t, f in zip(t_wall, track.field_body_ut, strict=True)]  # fmt: skip
    for panel in p["panels"]:
        ch, face, max_a = panel.get("channel"), panel.get("face"), panel.get("max_a")
        if ch not in step.loads_allowed or face not in FACES or not isinstance(max_a, int | float):
            raise ProcedureError(
                f"{where}: a panel needs channel (one of the procedure's loads), face ({', '.join(FACES)}) and max_a"
            )
        amps = np.round(panel_current(track, face, float(max_a)), 3)  # 1 mA resolution
        last = None
        for t, a in zip(t_wall, amps, strict=True):
            if last is None or abs(a - last) >= 0.002 or (a == 0.0 and last != 0.0):
                cmds.append(Command(float(t), "load", {"channel": ch, "current_a": float(a)}))
                last = a
        cmds.append(Command(p["duration_s"], "load", {"channel": ch, "current_a": 0.0}))
    return cmds, float(p["duration_s"])


@dataclass(frozen=True)
class RigTiming:
    """What the duration of a cage characterization depends on besides its parameters: the coil
    current slew limit and set-point interval (``[cage]`` of the rig configuration) and the
    reference magnetometer's sample rate. The defaults are those of the simulated cage."""

    max_slew_a_per_s: float = 10.0
    step_s: float = 0.05
    reference_rate_hz: float = 20.0


def rig_timing(cfg: RigConfig | None) -> RigTiming | None:
    """The timing of a rig configuration's cage (None without one: the defaults apply)."""
    if cfg is None or cfg.cage is None:
        return None
    rate = RigTiming().reference_rate_hz
    ref = cfg.devices.get(cfg.cage.reference or "")
    given = ref.get("rate_hz") if ref is not None else None
    if isinstance(given, int | float) and not isinstance(given, bool) and given > 0:
        rate = float(given)
    return RigTiming(cfg.cage.max_slew_a_per_s, cfg.cage.step_s, rate)


def characterization_duration_s(
    amplitude_a: float, samples: int, repeats: int, timing: RigTiming | None = None
) -> float:
    """Estimated wall time of ``characterize_cage`` (s): per sweep point the ramp (one set-point per
    ``step_s``, within the slew limit, through zero where the polarity flips), the transient wait
    and ``samples`` fresh reference readings (plus on average half a period until the first); then
    the ramp back to zero. Within 5 % of the measured time on the simulated cage (docs/procedures.md)."""
    from rig.cage.characterize import TRANSIENT_S, sweep_points  # the sweep itself, not a copy
    from rig.cage.limits import CageLimits, plan_ramp

    t = timing or RigTiming()
    big = 1e6  # the planner checks current limits; the dry run checks them elsewhere
    limits = CageLimits((big, big, big), big, t.max_slew_a_per_s, t.step_s)
    points = np.tile(sweep_points(amplitude_a), (repeats, 1))
    here = np.zeros(3)
    setpoints = 0
    for target in [*points, np.zeros(3)]:
        setpoints += len(plan_ramp(here, target, limits))
        here = target
    per_point = TRANSIENT_S + (samples + 0.5) / t.reference_rate_hz
    return setpoints * t.step_s + len(points) * per_point


def step_duration(step: Step, timing: RigTiming | None = None) -> float:
    """Nominal duration of a step (s): field steps from their parameters, a cage characterization
    from its sweep (:func:`characterization_duration_s`); 0 for instantaneous steps."""
    p = step.params
    if step.kind == "characterize_cage":
        return characterization_duration_s(p["amplitude_a"], p["samples"], p["repeats"], timing)
    if step.kind == "orbit_replay":
        return float(p["duration_s"])
    if step.kind in ("null_field", "set_field", "hold"):
        return float(p["hold_s"])
    if step.kind in ("sphere_sweep", "axis_sweep", "rotate", "live_calibrate"):
        return len(field_sequence(step)) * float(p["dwell_s"])
    return 0.0


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


def compile_step(step: Step, base: Path, timing: RigTiming | None = None) -> StepPlan:
    """The commands of one step."""
    cmds: list[Command] = []
    if step.kind == "orbit_replay":
        cmds, duration = orbit_commands(step)
        cmds.append(Command(duration, "end", {}))
    elif step.kind in FIELD_STEPS:
        duration = step_duration(step)
        for t, f in field_sequence(step):
            cmds.append(
                Command(
                    t,
                    "field",
                    {"field_ut": [float(v) for v in f], "trim": step.params.get("trim") == "yes"},
                )
            )
        for ch, (kind, params) in step.loads.items():
            for t, amps in load_profile(kind, params, duration, base):
                cmds.append(Command(t, "load", {"channel": ch, "current_a": float(amps)}))
            cmds.append(Command(duration, "load", {"channel": ch, "current_a": 0.0}))
        cmds.append(Command(duration, "end", {}))
    else:  # one command; a characterization takes its time inside it (no wait is planned)
        duration = step_duration(step, timing)
        cmds.append(Command(0.0, step.kind, dict(step.params)))
    cmds.sort(key=lambda c: (c.t_s, c.kind != "field"))
    return StepPlan(step, duration, tuple(cmds))


def compile_plan(proc: Procedure, timing: RigTiming | None = None) -> Iterator[StepPlan]:
    """The plan: a generator of step plans (so a run can start before all are compiled)."""
    for step in proc.steps:
        yield compile_step(step, proc.path.parent, timing)


@dataclass
class DryRun:
    """What a procedure will do: duration, peaks and limit violations."""

    duration_s: float = 0.0
    peak_field_ut: float = 0.0
    peak_current_a: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    peak_load_a: dict[str, float] = field(default_factory=dict)
    violations: list[str] = field(default_factory=list)
    timeline: list[tuple[float, str, str]] = field(default_factory=list)  # start, step, summary


ABSOLUTE_MAX_FIELD_UT = 1000.0
"""Checked with or without a rig configuration: no cage this software drives makes 1 mT (the
language bounds sweep magnitudes to the same value); a field beyond it is a typo (nT written as uT)."""


def dry_run(
    proc: Procedure,
    k_ut_per_a: Array | None = None,
    b0_ut: Array | None = None,
    max_current_a: tuple[float, float, float] | None = None,
    max_field_ut: float | None = None,
    load_max_a: dict[str, float] | None = None,
    timing: RigTiming | None = None,
) -> DryRun:
    """Check a procedure without hardware; currents need the cage model (``k_ut_per_a``, ``b0_ut``).
    Fields beyond :data:`ABSOLUTE_MAX_FIELD_UT` are violations even without the rig's limits."""
    out = DryRun()
    t = 0.0
    for plan in compile_plan(proc, timing):
        s = plan.step
        fields = [np.array(c.payload["field_ut"]) for c in plan.commands if c.kind == "field"]
        summary = (
            f"{s.kind}"
            + (f", {len(fields)} fields" if fields else "")
            + (f", loads {', '.join(s.loads)}" if s.loads else "")
        )
        out.timeline.append((t, s.name, summary))
        for f in fields:
            mag = float(np.linalg.norm(f))
            out.peak_field_ut = max(out.peak_field_ut, mag)
            if max_field_ut is not None and mag > max_field_ut + 1e-9:
                out.violations.append(
                    f"{s.where}: step {s.index + 1} ({s.name}): |B| = {mag:.1f} uT exceeds the {max_field_ut:g} uT limit"
                )
            elif mag > ABSOLUTE_MAX_FIELD_UT + 1e-9:
                out.violations.append(
                    f"{s.where}: step {s.index + 1} ({s.name}): |B| = {mag:.1f} uT exceeds {ABSOLUTE_MAX_FIELD_UT:g} uT, more than any cage makes: fields are in uT (nT by mistake?)"
                )
            if k_ut_per_a is not None:
                currents = np.linalg.solve(k_ut_per_a, f - (b0_ut if b0_ut is not None else 0.0))
                for ax in range(3):
                    out.peak_current_a[ax] = max(out.peak_current_a[ax], abs(float(currents[ax])))
                    if max_current_a is not None and abs(currents[ax]) > max_current_a[ax] + 1e-9:
                        out.violations.append(
                            f"{s.where}: step {s.index + 1} ({s.name}): field {np.round(f, 1).tolist()} uT needs {currents[ax]:+.2f} A on axis {'xyz'[ax]}, beyond {max_current_a[ax]:g} A"
                        )
        for c in plan.commands:
            if c.kind == "characterize_cage":  # +-amplitude on every axis
                amps = float(c.payload["amplitude_a"])
                for ax in range(3):
                    out.peak_current_a[ax] = max(out.peak_current_a[ax], amps)
                    if max_current_a is not None and amps > max_current_a[ax] + 1e-9:
                        out.violations.append(
                            f"{s.where}: step {s.index + 1} ({s.name}): amplitude {amps:g} A on axis {'xyz'[ax]} is beyond {max_current_a[ax]:g} A"
                        )
            if c.kind == "load":
                ch, amps = c.payload["channel"], abs(c.payload["current_a"])
                out.peak_load_a[ch] = max(out.peak_load_a.get(ch, 0.0), amps)
                limit = (load_max_a or {}).get(ch)
                if limit is not None and amps > limit + 1e-9:
                    out.violations.append(
                        f"{s.where}: step {s.index + 1} ({s.name}): load {ch} {amps:g} A exceeds {limit:g} A"
                    )
        t += plan.duration_s
    out.duration_s = t
    # keep each violation once (sweeps repeat the same message per point)
    out.violations = list(dict.fromkeys(out.violations))
    return out
