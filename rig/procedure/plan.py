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
    FieldCommand,
    LoadCommand,
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
    return RigTiming(cfg.cage.ramp_slew_a_per_s, cfg.cage.step_s, rate, cfg.cage.max_field_ut)


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
    peak_margin_a: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    """Per axis, the uncertainty margin (A) at the peak: 3 sigma of the cage model, or what an
    ambient field not yet characterized may add."""
    violations: list[str] = field(default_factory=list)
    at_risk: list[str] = field(default_factory=list)
    """Limits that hold with the model as it is but not with its margin when the margin is an
    unknown ambient field (no characterization yet): the run finds out after characterizing."""
    timeline: list[tuple[float, str, str]] = field(default_factory=list)  # start, step, summary


MODEL_SIGMAS = 3.0
"""Coil currents are judged at the cage model's value plus this many of its standard deviations."""
EARTH_MAX_UT = 66.0
"""The largest geomagnetic field on Earth (uT, near the south magnetic pole): the ambient field a
cage without a characterization may have to cancel."""


@dataclass(frozen=True)
class CageModelUncertainty:
    """How well the dry run knows the cage: 1-sigma of the coil matrix (uT/A) and ambient (uT)
    from a characterization, or, with none yet, an ambient field of unknown direction up to
    ``unknown_ambient_ut``."""

    k_sigma: Array | None = None
    b0_sigma_ut: Array | None = None
    unknown_ambient_ut: float = 0.0


def current_margin_a(
    k_ut_per_a: Array, currents_a: npt.ArrayLike, u: CageModelUncertainty
) -> tuple[Array, Array]:
    """Per axis, (3-sigma margin from the characterization, margin from an unknown ambient) in A
    for ``currents_a``: ``|K^-1| (3 sigma_b0 + 3 |sigma_K| |I|)`` and ``B_max |row_i K^-1|``."""
    inv = np.linalg.inv(k_ut_per_a)
    sigma_field = np.zeros(3)
    if u.b0_sigma_ut is not None:
        sigma_field = sigma_field + np.abs(u.b0_sigma_ut)
    if u.k_sigma is not None:
        sigma_field = sigma_field + np.abs(u.k_sigma) @ np.abs(np.asarray(currents_a, float))
    model = MODEL_SIGMAS * (np.abs(inv) @ sigma_field)
    ambient = u.unknown_ambient_ut * np.linalg.norm(inv, axis=1)
    return model, ambient


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
    uncertainty: CageModelUncertainty | None = None,
) -> DryRun:
    """Check a procedure without hardware; currents need the cage model (``k_ut_per_a``, ``b0_ut``).
    Fields beyond :data:`ABSOLUTE_MAX_FIELD_UT` are violations even without the rig's limits.
    With ``uncertainty``, a coil current is a violation when it exceeds its limit with the
    model's 3-sigma margin, and at risk when only an unknown ambient field would take it there."""
    walk = _DryRunWalk(k_ut_per_a, b0_ut, max_current_a, max_field_ut, load_max_a or {},
                       uncertainty or CageModelUncertainty())  # fmt: skip
    for plan in compile_plan(proc, timing):
        walk.step(plan)
    return walk.result()


def envelope_fields(radius_ut: float | None, k_ut_per_a: Array | None) -> list[Array]:
    """The fields on a sphere of ``radius_ut`` (uT) that drive each coil hardest, both signs:
    along the rows of the inverse coil matrix when it is known (the coil currents are linear in
    the field), else along the cage axes. None: no fields."""
    if radius_ut is None:
        return []
    rows = np.eye(3) if k_ut_per_a is None else np.linalg.inv(k_ut_per_a)
    dirs = [r / np.linalg.norm(r) for r in rows]
    return [sign * radius_ut * d for d in dirs for sign in (1.0, -1.0)]


@dataclass
class _DryRunWalk:
    """:func:`dry_run`'s walk through a plan, one step at a time."""

    k_ut_per_a: Array | None
    b0_ut: Array | None
    max_current_a: tuple[float, float, float] | None
    max_field_ut: float | None
    load_max_a: dict[str, float]
    given: CageModelUncertainty
    out: DryRun = field(default_factory=lambda: DryRun())
    t: float = 0.0
    risky: dict[tuple[int, int], tuple[int, float, str]] = field(default_factory=dict)
    """(step, axis): count, worst A, text."""

    def __post_init__(self) -> None:
        # no unknown ambient until the run measures the ambient it cancels
        self.u = CageModelUncertainty(self.given.k_sigma, self.given.b0_sigma_ut)

    def step(self, plan: StepPlan) -> None:
        """Walk one step: its fields, its own peak current, its loads, the time it takes."""
        s = plan.step
        fields = [
            np.array(c.payload["field_ut"]) for c in plan.commands if isinstance(c, FieldCommand)
        ]
        fields += envelope_fields(KINDS[s.kind].field_envelope_ut(s), self.k_ut_per_a)
        summary = (
            f"{s.kind}"
            + (f", {len(fields)} fields" if fields else "")
            + (f", loads {', '.join(s.loads)}" if s.loads else "")
        )
        self.out.timeline.append((self.t, s.name, summary))
        for f in fields:
            self._field(s, f)
        self._kind_peak(s)
        for c in plan.commands:
            if isinstance(c, LoadCommand):
                self._load(s, c.payload["channel"], abs(c.payload["current_a"]))
        for ch, amps in KINDS[s.kind].load_envelope_a(s).items():
            self._load(s, ch, amps)
        if KINDS[s.kind].measures_cage_model:  # ... the run measures the ambient it cancels
            self.u = self.given
        self.t += plan.duration_s
        self._duration(s)

    def _field(self, s: Step, f: Array) -> None:
        out = self.out
        mag = float(np.linalg.norm(f))
        out.peak_field_ut = max(out.peak_field_ut, mag)
        # until the run measures the lab field (a step that characterizes the cage), the coils
        # do not cancel it: the field made is the one asked plus an ambient of up to the given
        unmeasured = self.given.unknown_ambient_ut if self.u is not self.given else 0.0
        if self.max_field_ut is not None and mag > self.max_field_ut + 1e-9:
            out.violations.append(
                f"{s.where}: step {s.index + 1} ({s.name}): |B| = {mag:.1f} uT exceeds the {self.max_field_ut:g} uT limit"
            )
        elif self.max_field_ut is not None and mag + unmeasured > self.max_field_ut + 1e-9:
            out.violations.append(
                f"{s.where}: step {s.index + 1} ({s.name}): |B| = {mag:.1f} uT with the lab field"
                f" not yet measured (up to {unmeasured:g} uT, the cage not characterized) may"
                f" reach {mag + unmeasured:.1f} uT, beyond the {self.max_field_ut:g} uT limit:"
                " characterize the cage first (rig run cage-characterization, or a"
                " characterize_cage step before it) or ask for a smaller field"
            )
        elif mag > ABSOLUTE_MAX_FIELD_UT + 1e-9:
            out.violations.append(
                f"{s.where}: step {s.index + 1} ({s.name}): |B| = {mag:.1f} uT exceeds {ABSOLUTE_MAX_FIELD_UT:g} uT, more than any cage makes: fields are in uT (nT by mistake?)"
            )
        if self.k_ut_per_a is not None:
            b0 = self.b0_ut if self.b0_ut is not None else 0.0
            currents = np.linalg.solve(self.k_ut_per_a, f - b0)
            model_a, ambient_a = current_margin_a(self.k_ut_per_a, currents, self.u)
            for ax in range(3):
                self._axis(s, f, ax, float(currents[ax]), float(model_a[ax]), float(ambient_a[ax]))

    def _axis(self, s: Step, f: Array, ax: int, current: float, model: float,
              ambient: float) -> None:  # fmt: skip
        """One axis's current for field ``f``: the peaks, then a violation or a risk."""
        out, amps = self.out, abs(current)
        if amps + model + ambient >= out.peak_current_a[ax] + out.peak_margin_a[ax]:
            out.peak_margin_a[ax] = float(model + ambient)
        out.peak_current_a[ax] = max(out.peak_current_a[ax], amps)
        if self.max_current_a is None:
            return
        limit = self.max_current_a[ax]
        where = f"{s.where}: step {s.index + 1} ({s.name}): field {np.round(f, 1).tolist()} uT needs {current:+.2f} A on axis {'xyz'[ax]}"
        if amps + model > limit + 1e-9:
            margin = (
                f" (+-{model:.2f} A at {MODEL_SIGMAS:g} sigma of the cage model)"
                if model > 0
                else ""
            )
            out.violations.append(f"{where}{margin}, beyond {limit:g} A")
        elif amps + model + ambient > limit + 1e-9:
            worst = amps + model + ambient
            count, before, text = self.risky.get((s.index, ax), (0, 0.0, ""))
            if worst >= before:
                before, text = (
                    worst,
                    f"{where}; with an ambient field of up to {self.u.unknown_ambient_ut:g} uT (not characterized yet) up to {worst:.2f} A, beyond {limit:g} A",
                )
            self.risky[(s.index, ax)] = (count + 1, before, text)

    def _kind_peak(self, s: Step) -> None:
        """A kind that drives coils outside field commands: +-peak on every axis."""
        peak = KINDS[s.kind].peak_coil_current_a(s)
        if peak is None:
            return
        for ax in range(3):
            self.out.peak_current_a[ax] = max(self.out.peak_current_a[ax], peak)
            if self.max_current_a is not None and peak > self.max_current_a[ax] + 1e-9:
                self.out.violations.append(
                    f"{s.where}: step {s.index + 1} ({s.name}): amplitude {peak:g} A on axis {'xyz'[ax]} is beyond {self.max_current_a[ax]:g} A"
                )

    def _load(self, s: Step, ch: str, amps: float) -> None:
        self.out.peak_load_a[ch] = max(self.out.peak_load_a.get(ch, 0.0), amps)
        limit = self.load_max_a.get(ch)
        if limit is not None and amps > limit + 1e-9:
            self.out.violations.append(
                f"{s.where}: step {s.index + 1} ({s.name}): load {ch} {amps:g} A exceeds {limit:g} A"
            )

    def _duration(self, s: Step) -> None:
        t, out = self.t, self.out
        if t > MAX_TOTAL_DURATION_S and not any(
            "MAX_TOTAL_DURATION_S" in v for v in out.violations
        ):
            out.violations.append(  # parse_procedure checked it with the default timing
                f"{s.where}: step {s.index + 1} ({s.name}): the procedure's duration reaches"
                f" {t / 86400:.2f} days here with this rig's timing, beyond the"
                f" {MAX_TOTAL_DURATION_S / 86400:g}-day limit (MAX_TOTAL_DURATION_S)"
            )

    def result(self) -> DryRun:
        """The dry run, each violation once (sweeps repeat the same message per point)."""
        out = self.out
        out.duration_s = self.t
        out.violations = list(dict.fromkeys(out.violations))
        out.at_risk = [
            text + (f" (the worst of {n} fields)" if n > 1 else "")
            for n, _, text in self.risky.values()
        ]
        return out
