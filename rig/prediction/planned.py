"""The samples a ``calibrate`` step will be given, known from the plan before any current flows.

A field step holds each set-point for its dwell after the ramp to it (the run's clock restarts at
the ramp's end), its load profiles step at their own planned times, and the DUT samples at its
rate throughout. A calibration keeps the samples outside every change (a field or load
set-point) from 1.5 reference periods before it to ``settle_s`` after it (``rig.analysis``'s
settling); tracked set-points (orbit replay) are not changes. So the kept samples, their fields
and their load currents follow from the plan alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from rig.config import RigConfig
from rig.prediction.background import Background
from rig.procedure.plan import compile_step
from rig.steps import field_kinds
from rig.steps.vocabulary import Command, FieldCommand, LoadCommand, Procedure, RigTiming, Step

Array = npt.NDArray[np.float64]
DEFAULT_DUT_RATE_HZ = 20.0
"""A DUT's sample rate when the rig configuration gives none (Hz)."""
EARLY_REFERENCE_PERIODS = 1.5
"""A change's window opens this many reference periods before it (``rig.analysis``)."""


@dataclass(frozen=True)
class PlannedData:
    """What a calibrate step will fit: per kept sample the field set (uT, cage frame) and the
    load currents commanded (A, ``channels`` order), and the steps they come from."""

    field_ut: Array
    telemetry: Array
    channels: tuple[str, ...]
    steps: tuple[str, ...]
    seconds: float
    """The selected steps' planned time (s, ramps not counted)."""

    @property
    def n(self) -> int:
        """How many samples."""
        return len(self.field_ut)


def selected_steps(proc: Procedure, calibrate: Step) -> list[Step]:
    """The steps a calibrate step fits: those it names, else every field step before it."""
    before = [s for s in proc.steps if s.index < calibrate.index]
    names = list(calibrate.params.get("steps") or [])
    if names:
        return [s for s in before if s.name in names]
    kinds = field_kinds()
    return [s for s in before if s.kind in kinds]


def planned_data(proc: Procedure, calibrate: Step, timing: RigTiming, dut_rate_hz: float,
                 base: Path | None = None, stops_s: dict[str, float] | None = None,
                 background: Background | None = None) -> PlannedData:  # fmt: skip
    """The samples ``calibrate`` (a step of ``proc``) will be given by a run of the plan, the DUT
    sampling at ``dut_rate_hz`` and the reference at ``timing.reference_rate_hz``; a step named in
    ``stops_s`` ends that many seconds in (a live calibration stopping on its targets); the field
    the cage leaves at zero (``background``) added to each step's set-points."""
    channels = tuple(str(c) for c in calibrate.params.get("telemetry") or ())
    settle_s = float(calibrate.params.get("settle_s", 0.25))
    early_s = EARLY_REFERENCE_PERIODS / timing.reference_rate_hz
    fields, loads, names, seconds = [], [], [], 0.0
    for step in selected_steps(proc, calibrate):
        plan = compile_step(step, base or proc.path.parent, timing)
        t, f, u = step_samples(plan.commands, plan.duration_s, channels, dut_rate_hz,
                               settle_s, early_s)  # fmt: skip
        end = min(plan.duration_s, (stops_s or {}).get(step.name, plan.duration_s))
        bg = background.for_step(proc, step) if background is not None else np.zeros(3)
        fields.append(f[t <= end] + bg)
        loads.append(u[t <= end])
        names.append(step.name)
        seconds += end
    if not fields:
        return PlannedData(np.zeros((0, 3)), np.zeros((0, len(channels))), channels, (), 0.0)
    return PlannedData(np.vstack(fields), np.vstack(loads), channels, tuple(names), seconds)


def step_samples(commands: tuple[Command, ...], duration_s: float, channels: tuple[str, ...],
                 rate_hz: float, settle_s: float, early_s: float) -> tuple[Array, Array, Array]:  # fmt: skip
    """One step's kept samples: (times s from the step's start (N,), fields (N, 3), load
    currents (N, J))."""
    t = np.arange(0.5 / rate_hz, duration_s, 1.0 / rate_hz)
    field_times, field_values = [], []
    load_times: dict[str, list[float]] = {ch: [] for ch in channels}
    load_values: dict[str, list[float]] = {ch: [] for ch in channels}
    changes = []
    for cmd in commands:
        if isinstance(cmd, FieldCommand):
            field_times.append(cmd.t_s)
            field_values.append(cmd.payload["field_ut"])
        elif isinstance(cmd, LoadCommand) and cmd.payload["channel"] in load_times:
            load_times[cmd.payload["channel"]].append(cmd.t_s)
            load_values[cmd.payload["channel"]].append(cmd.payload["current_a"])
        if isinstance(cmd, FieldCommand | LoadCommand) and not cmd.payload.get("track"):
            changes.append(cmd.t_s)
    if not field_times:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, len(channels)))
    keep = t >= field_times[0]
    for c in changes:
        keep &= ~((t >= c - early_s) & (t < c + settle_s))
    t = t[keep]
    fields = np.asarray(field_values, float)[np.searchsorted(field_times, t, side="right") - 1]
    loads = np.zeros((len(t), len(channels)))
    for j, ch in enumerate(channels):
        if load_times[ch]:
            idx = np.searchsorted(load_times[ch], t, side="right") - 1
            loads[:, j] = np.where(idx >= 0, np.asarray(load_values[ch])[np.maximum(idx, 0)], 0.0)
    return t, fields, loads


def dut_rate_hz(cfg: RigConfig | None, dut: str) -> float:
    """The DUT's sample rate from the rig configuration (Hz; 20 when it gives none)."""
    if cfg is not None and dut in cfg.devices and cfg.devices[dut].get("rate_hz"):
        return float(cfg.devices[dut].get("rate_hz"))
    return DEFAULT_DUT_RATE_HZ
