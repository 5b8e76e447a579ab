"""Compile a procedure into a plan: per step, a timeline of small commands.

A plan is data, so it can be dry-run (:func:`dry_run`): duration, peak currents and fields, and
limit violations are known before any hardware is touched.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from rig.steps import KINDS
from rig.steps.characterize_cage import characterization_duration_s
from rig.steps.geometry import fibonacci_directions
from rig.steps.vocabulary import (
    MAX_TOTAL_DURATION_S,
    Command,
    Procedure,
    RigTiming,
    Step,
    StepPlan,
)

if TYPE_CHECKING:
    from rig.config import RigConfig

Array = npt.NDArray[np.float64]
__all__ = ["Command", "RigTiming", "StepPlan", "characterization_duration_s", "compile_plan",
           "dry_run", "fibonacci_directions", "rig_timing", "step_duration"]  # fmt: skip


def rig_timing(cfg: RigConfig | None) -> RigTiming | None:
    """What a plan needs to know of a rig configuration's cage (None without one: defaults)."""
    if cfg is None or cfg.cage is None:
        return None
    rate = RigTiming().reference_rate_hz
    ref = cfg.devices.get(cfg.cage.reference or "")
    given = ref.get("rate_hz") if ref is not None else None
    if isinstance(given, int | float) and not isinstance(given, bool) and given > 0:
        rate = float(given)
    return RigTiming(cfg.cage.max_slew_a_per_s, cfg.cage.step_s, rate, cfg.cage.max_field_ut)


def step_duration(step: Step, timing: RigTiming | None = None) -> float:
    """Nominal duration of a step (s), as its kind works it out; 0 for instantaneous steps."""
    return KINDS[step.kind].duration_s(step, timing or RigTiming())


def compile_step(step: Step, base: Path, timing: RigTiming | None = None) -> StepPlan:
    """The commands of one step, time-ordered (a field before a load at the same time)."""
    cmds, duration = KINDS[step.kind].compile(step, base, timing or RigTiming())
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
        peak = KINDS[s.kind].peak_coil_current_a(s)
        if peak is not None:  # +-peak on every axis, outside field commands
            for ax in range(3):
                out.peak_current_a[ax] = max(out.peak_current_a[ax], peak)
                if max_current_a is not None and peak > max_current_a[ax] + 1e-9:
                    out.violations.append(
                        f"{s.where}: step {s.index + 1} ({s.name}): amplitude {peak:g} A on axis {'xyz'[ax]} is beyond {max_current_a[ax]:g} A"
                    )
        for c in plan.commands:
            if c.kind == "load":
                ch, amps = c.payload["channel"], abs(c.payload["current_a"])
                out.peak_load_a[ch] = max(out.peak_load_a.get(ch, 0.0), amps)
                limit = (load_max_a or {}).get(ch)
                if limit is not None and amps > limit + 1e-9:
                    out.violations.append(
                        f"{s.where}: step {s.index + 1} ({s.name}): load {ch} {amps:g} A exceeds {limit:g} A"
                    )
        t += plan.duration_s
        if t > MAX_TOTAL_DURATION_S and not any(
            "MAX_TOTAL_DURATION_S" in v for v in out.violations
        ):
            out.violations.append(  # parse_procedure checked it with the default timing
                f"{s.where}: step {s.index + 1} ({s.name}): the procedure's duration reaches"
                f" {t / 86400:.2f} days here with this rig's timing, beyond the"
                f" {MAX_TOTAL_DURATION_S / 86400:g}-day limit (MAX_TOTAL_DURATION_S)"
            )
    out.duration_s = t
    # keep each violation once (sweeps repeat the same message per point)
    out.violations = list(dict.fromkeys(out.violations))
    return out
