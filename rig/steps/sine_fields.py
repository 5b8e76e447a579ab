"""Sine fields on the cage's axes, as ``frequency_response`` and ``cage_response`` make and read
them: each axis holds a bias (no coil changes polarity mid-sine: a relay flip would be a step),
then at each frequency a sine on top as tracked set-points at ``rate_hz``, ``settle_cycles`` left
out and the rest fitted; and what the rig allows of them (its slew limit, the cage's measured
bandwidth)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rig.characterization.frequency import Phasor, first_order, phasor
from rig.errors import RigError
from rig.steps.base import Array, CageAbilities, FieldStepKind, RunContext, load_commands
from rig.steps.vocabulary import (
    MAX_FIELD_SETPOINTS_PER_STEP,
    Command,
    EndCommand,
    FieldCommand,
    ProcedureError,
    RigTiming,
    Step,
    StepParam,
)

AXES = "xyz"

SINE_PARAMS: dict[str, StepParam] = {
    "frequencies_hz": StepParam("list_float", [0.1, 0.2, 0.5, 1.0, 2.0]),
    "axes": StepParam("str", "xyz"),
    "amplitude_ut": StepParam("float", 10.0, 0.1, 1000.0),
    "bias_ut": StepParam("float", 30.0, 0.0, 1000.0),
    "cycles": StepParam("int", 4, 1, 10000),
    "min_s": StepParam("float", 8.0, 0.0, 86400.0),
    "settle_cycles": StepParam("int", 1, 0, 100),
    "settle_s": StepParam("float", 2.0, 0.0, 600.0),
    "rate_hz": StepParam("float", 25.0, 1.0, 200.0),
}
"""The parameters of a step of sines (docs/procedures.md)."""


@dataclass(frozen=True)
class Segment:
    """One sine in a step's plan: its axis (0-2), frequency (Hz), start and length (s from the
    step's start)."""

    axis: int
    f_hz: float
    start_s: float
    length_s: float


def validate_sines(params: dict[str, Any], where: str) -> None:
    """Refuse (ProcedureError naming ``where`` and the fix) sines the step cannot make."""
    axes = params["axes"]
    if not axes or any(a not in AXES for a in axes) or len(set(axes)) != len(axes):
        raise ProcedureError(f"{where}: axes is some of x, y, z, each once (e.g. xyz)")
    if params["bias_ut"] <= params["amplitude_ut"]:
        raise ProcedureError(f"{where}: bias_ut must exceed amplitude_ut, so that no coil"
                             " changes polarity during a sine")  # fmt: skip
    top = params["rate_hz"] / 5.0
    if not params["frequencies_hz"] or any(not 0 < f <= top for f in params["frequencies_hz"]):
        raise ProcedureError(f"{where}: frequencies_hz must be above 0 and at most rate_hz / 5"
                             f" ({top:g} Hz: five set-points per cycle)")  # fmt: skip
    setpoints = params["rate_hz"] * sum(s.length_s for s in segments(params))
    if setpoints > MAX_FIELD_SETPOINTS_PER_STEP:
        raise ProcedureError(f"{where}: {setpoints:.0f} set-points, more than"
                             f" {MAX_FIELD_SETPOINTS_PER_STEP} (MAX_FIELD_SETPOINTS_PER_STEP):"
                             " fewer cycles at the lowest frequencies")  # fmt: skip


def segments(params: dict[str, Any]) -> list[Segment]:
    """Each sine of a step with these parameters, in the step's time: ``cycles`` fitted, or as
    many as last ``min_s`` (a fast sine's few cycles are soon over), after ``settle_cycles``."""
    t, out = 0.0, []
    for axis in params["axes"]:
        t += float(params["settle_s"])
        for f in params["frequencies_hz"]:
            fitted = max(int(params["cycles"]), math.ceil(float(params["min_s"]) * f - 1e-9))
            length = (fitted + int(params["settle_cycles"])) / float(f)
            out.append(Segment(AXES.index(axis), float(f), t, length))
            t += length
    return out


def duration_s(params: dict[str, Any]) -> float:
    """The step's length (s): its last sine's end."""
    last = segments(params)[-1]
    return last.start_s + last.length_s


def bias_fields(params: dict[str, Any]) -> list[tuple[float, Array]]:
    """Each axis's bias (s from the step's start, field uT) as its sines start."""
    starts: dict[int, float] = {}
    for s in segments(params):
        starts.setdefault(s.axis, s.start_s - float(params["settle_s"]))
    out = []
    for axis, t in starts.items():
        v = np.zeros(3)
        v[axis] = float(params["bias_ut"])
        out.append((t, v))
    return out


def setpoint_count(s: Segment, rate_hz: float) -> int:
    """How many set-points a segment is planned with: one every ``1 / rate_hz`` s from its start,
    the last at or before its end (rounded, 4.25 s at 47 Hz put the last one 5 ms past the end:
    after the next axis's bias, whose field it then put back with a ramp of 0.4 s)."""
    return math.floor(s.length_s * rate_hz + 1e-9)


def sine_commands(params: dict[str, Any]) -> list[Command]:
    """The sines' tracked set-points (each tagged with its ``segment``: axis, frequency)."""
    rate, amp, bias = float(params["rate_hz"]), float(params["amplitude_ut"]), params["bias_ut"]
    cmds: list[Command] = []
    for s in segments(params):
        for k in range(1, setpoint_count(s, rate) + 1):
            v = np.zeros(3)
            v[s.axis] = float(bias) + amp * math.sin(2.0 * math.pi * s.f_hz * k / rate)
            cmds.append(FieldCommand(s.start_s + k / rate,
                                {"field_ut": [float(x) for x in v], "trim": False, "track": True, "keep_time": True,
                                 "segment": [s.axis, s.f_hz]}))  # fmt: skip
    return cmds


def _fitted(step: Step, sent: list[tuple[float, dict[str, Any]]],
            s: Segment) -> list[tuple[float, dict[str, Any]]]:  # fmt: skip
    """The segment's fitted set-points as sent (time s, payload): those planned after its
    ``settle_cycles`` (by their plan time; a run recorded without it: all but as many as those
    cycles hold). RigError when fewer than 5 were sent (the step ended early)."""
    p = step.params
    rows = [(t, pl) for t, pl in sent if pl.get("segment") == [s.axis, s.f_hz]]
    settled_from = s.start_s + int(p["settle_cycles"]) / s.f_hz
    if rows and all("t_plan" in pl for _, pl in rows):
        rows = [(t, pl) for t, pl in rows if pl["t_plan"] > settled_from - 1e-9]
    else:
        rows = rows[round(int(p["settle_cycles"]) / s.f_hz * float(p["rate_hz"])) :]
    if len(rows) < 5:
        raise RigError(f"{step.kind} '{step.name}': the {s.f_hz:g} Hz sine on"
                       f" {AXES[s.axis]} was not sent (the step ended early)")  # fmt: skip
    return rows


def planned_setpoints(step: Step, s: Segment) -> int:
    """How many set-points the segment's fitted cycles were planned with (those :func:`_fitted`
    keeps: planned after its settle cycles)."""
    p = step.params
    rate = float(p["rate_hz"])
    settle_s = int(p["settle_cycles"]) / s.f_hz
    return sum(1 for k in range(1, setpoint_count(s, rate) + 1) if k / rate > settle_s - 1e-9)


def commanded(step: Step, sent: list[tuple[float, dict[str, Any]]], s: Segment) -> Array:
    """Rows (t s, field uT along the sine's axis) of the segment's fitted set-points as sent
    (``sent``: the step's field commands, time and payload); RigError when they were not."""
    return np.asarray([(t, pl["field_ut"][s.axis]) for t, pl in _fitted(step, sent, s)], float)


MAX_SLIP_CYCLES = 0.005
"""A sine whose set-points slipped behind their plan by more than this fraction of its period
within its fitted cycles (a busy computer held them back: :class:`rig.engine.schedule.TrackPace`)
was not made as a sine at its frequency; its point is not judged. Seen on a busy computer: the
field made read as 0.06-1.25 of the field asked where the cage made 0.82-1.0 (issue 54)."""


def slip_s(fitted: list[tuple[float, dict[str, Any]]]) -> float:
    """How far (s) a segment's ``fitted`` set-points (time s, payload) slipped behind their plan
    from the first to the last (due time less plan time; 0 for a run recorded without them)."""
    lag = [pl["t_due"] - pl["t_plan"] for _, pl in fitted if "t_due" in pl and "t_plan" in pl]
    return max(lag) - min(lag) if lag else 0.0


MIN_SENT = 0.5
"""A sine made of fewer than this fraction of its planned set-points (the rest skipped, each due
when the next one was: a busy computer) is too coarse a staircase to be judged."""


def slipped(step: Step, sent: list[tuple[float, dict[str, Any]]], s: Segment) -> str | None:
    """Why the segment's point is not judged, or None: its set-points slipped more than
    :data:`MAX_SLIP_CYCLES` of a period, or fewer than :data:`MIN_SENT` of them were sent."""
    fitted = _fitted(step, sent, s)
    w = slip_s(fitted)
    where = f"{AXES[s.axis]} {s.f_hz:g} Hz"
    if w * s.f_hz > MAX_SLIP_CYCLES:
        return f"{where}: set-points slipped {w:.3g} s ({100 * w * s.f_hz:.0f} % of a period)"
    made, planned = len(fitted), planned_setpoints(step, s)
    if made < MIN_SENT * planned:
        return f"{where}: {planned - made} of {planned} set-points skipped"
    return None


def sent_sines(reader: Any, step: Step) -> list[tuple[float, dict[str, Any]]]:
    """The step's sine set-points as recorded (time s, payload)."""
    return [(t, pl) for t, s, k, pl in reader.commands()
            if s == step.index and k == "field" and "segment" in pl]  # fmt: skip


def within(rows: Array, span: tuple[float, float]) -> Array:
    """The rows (first column: time s) within ``span`` (s, end excluded)."""
    return rows[(rows[:, 0] >= span[0]) & (rows[:, 0] < span[1])]


def span_of(cmds: Array, rate_hz: float) -> tuple[float, float]:
    """The time (s) the fitted set-points cover: the first to one period after the last."""
    return float(cmds[0, 0]), float(cmds[-1, 0] + 1.0 / rate_hz)


def staircase(t_s: Array, rate_hz: float, f_hz: float) -> tuple[float, ...]:
    """The set-points' staircase lines (the set-point rate and its double, plus and minus the
    sine's frequency) as a device sampling at times ``t_s`` sees them: aliased into its band,
    and left out where one lands on the sine itself or on zero (it cannot be told from them)."""
    if len(t_s) < 2:
        return ()
    fs = 1.0 / float(np.median(np.diff(t_s)))
    resolution = 1.5 / float(t_s[-1] - t_s[0])
    out: list[float] = []
    for line in (rate_hz - f_hz, rate_hz + f_hz, 2 * rate_hz - f_hz, 2 * rate_hz + f_hz):
        seen = abs(line - round(line / fs) * fs)
        apart = all(abs(seen - g) > resolution for g in (0.0, f_hz, *out))
        if apart and seen < 0.5 * fs - resolution:
            out.append(seen)
    return tuple(out)


@dataclass(frozen=True)
class ReferenceResponse:
    """The reference magnetometer's response as the rig configuration states it."""

    name: str
    tau_s: float
    integration_s: float

    def at(self, f_hz: float) -> complex:
        """Its transfer at ``f_hz``."""
        return first_order(self.tau_s, self.integration_s, f_hz)

    def note(self) -> str:
        """How the reference was taken, for the result."""
        if self.tau_s or self.integration_s:
            return (f"the reference's response (tau {self.tau_s:g} s, window"
                    f" {self.integration_s:g} s) removed")  # fmt: skip
        return "the reference taken as ideal (no response_tau_s given)"


def reference_response(ctx: RunContext, step: Step) -> ReferenceResponse:
    """The run's sampled reference and its configured response; RigError without one."""
    ref = ctx.proc.magnetometers.get("reference")
    if ref is None or ref not in ctx.samplers:
        raise RigError(f"{step.kind} '{step.name}' needs a sampled 'reference'")
    known = ctx.cfg.devices if ctx.cfg is not None else {}
    cfg = known.get(ref)
    tau = float(cfg.get("response_tau_s") or 0.0) if cfg is not None else 0.0
    window = float(cfg.get("response_integration_s") or 0.0) if cfg is not None else 0.0
    return ReferenceResponse(ref, tau, window)


def reference_phasor(rows: Array, rate_hz: float, f_hz: float, axis: int) -> Phasor:
    """The reference's phasor along ``axis`` from its rows (t s, x, y, z uT), its sigma from its
    own residuals near ``f_hz``."""
    return phasor(rows[:, 0], rows[:, 1 + axis], f_hz, staircase(rows[:, 0], rate_hz, f_hz))


def beyond_the_cage(step: Step, cage: CageAbilities) -> list[str]:
    """What the rig cannot make of a step's sines: a frequency above the cage's measured
    bandwidth on its axis (``cage_response`` in the cage record), or a sine whose slew on some
    coil exceeds ``max_slew_a_per_s`` (the controller would wait, and the sine would not be one)."""
    p, out = step.params, []
    limits = (cage.metrology.get("cage_response") or {}).get("limit_hz") or {}
    when = (cage.metrology.get("cage_response") or {}).get("date", "undated")
    for axis in p["axes"]:
        if limits.get(axis) is None or "cage_response" in cage.measured_before:
            continue
        top = float(limits[axis])
        over = [f for f in p["frequencies_hz"] if f > top + 1e-9]
        if over:
            out.append(f"{step.kind} '{step.name}': {', '.join(f'{f:g}' for f in over)} Hz on"
                       f" {axis} beyond the cage's measured bandwidth there ({top:.3g} Hz,"
                       f" cage_response of {when}): lower the frequencies, or measure the cage"
                       " again (rig run cage-response)")  # fmt: skip
    top_slew = cage.tracked_slew_a_per_s(float(p["rate_hz"]))
    if cage.k_ut_per_a is not None and top_slew is not None:
        inverse = np.linalg.inv(np.asarray(cage.k_ut_per_a, float))
        through = ("" if cage.coil_tau_s is None else f", {top_slew:.3g} A/s for set-points at"
                   f" {p['rate_hz']:g} Hz into the coils' {1e3 * cage.coil_tau_s:g} ms L/R")  # fmt: skip
        for axis in p["axes"]:
            amps = np.abs(inverse[:, AXES.index(axis)]) * float(p["amplitude_ut"])
            slew = 2.0 * math.pi * max(p["frequencies_hz"]) * float(np.max(amps))
            if slew > top_slew + 1e-9:
                out.append(f"{step.kind} '{step.name}': the {max(p['frequencies_hz']):g} Hz sine"
                           f" of {p['amplitude_ut']:g} uT on {axis} needs {slew:.3g} A/s, over the"
                           f" cage's max_slew_a_per_s ({cage.max_slew_a_per_s:g}{through}): a"
                           " smaller amplitude_ut or lower frequencies")  # fmt: skip
    return out + polarity_flips(step, cage)


def polarity_flips(step: Step, cage: CageAbilities) -> list[str]:
    """A sine that would take a coil's current through zero once the lab field is cancelled
    (``I = K^-1 (B - B0)``): behind polarity relays each crossing is a relay flip mid-sine (a step
    of the field, and arcing contacts), which ``bias_ut > amplitude_ut`` promises never happens.
    Nothing to say without relays or a measured lab field (one measured in the same run before
    the step is not known yet: :func:`rig.steps.beyond_the_cage`)."""
    if not cage.polarity_relays or cage.k_ut_per_a is None or cage.b0_ut is None:
        return []
    p, out = step.params, []
    inverse = np.linalg.inv(np.asarray(cage.k_ut_per_a, float))
    lo, hi = (
        float(p["bias_ut"]) - float(p["amplitude_ut"]),
        float(p["bias_ut"]) + float(p["amplitude_ut"]),
    )
    offset = inverse @ np.asarray(cage.b0_ut, float)  # the currents that cancel the lab field
    for axis in p["axes"]:
        a = AXES.index(axis)
        for coil in range(3):
            per_ut = float(inverse[coil, a])
            if abs(per_ut) < 1e-12:
                continue
            zero_ut = float(offset[coil]) / per_ut  # the field on the axis at which it is 0 A
            if lo - 1e-9 <= zero_ut <= hi + 1e-9:
                out.append(f"{step.kind} '{step.name}': the sine on {axis} ({lo:g}-{hi:g} uT)"
                           f" takes coil {AXES[coil]}'s current through zero at {zero_ut:.1f} uT"
                           " (the lab field cancelled): its polarity relay would flip every"
                           f" cycle; keep bias_ut - amplitude_ut above {zero_ut:.1f} uT or"
                           f" bias_ut + amplitude_ut below it")  # fmt: skip
    return out


class SineStepKind(FieldStepKind):
    """A step of sines (:data:`SINE_PARAMS`): each axis's bias, then its tracked set-points."""

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        validate_sines(params, where)

    def beyond_cage(self, step: Step, cage: CageAbilities) -> list[str]:
        return beyond_the_cage(step, cage)

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return duration_s(step.params)

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        """Each axis's bias as it starts (the sines are the step's own tracked set-points)."""
        return bias_fields(step.params)

    def compile(self, step: Step, base: Path, timing: RigTiming) -> tuple[list[Command], float]:
        duration = self.duration_s(step, timing)
        # the sines first: an axis's last set-point and the next axis's bias fall at one time,
        # and the planner's sort keeps this order (the bias after it, never the set-point after
        # the bias: that put the old axis's field back for the new one's settle_s, and its ramp
        # in the old sine's fitted cycles)
        cmds = sine_commands(step.params)
        cmds += [FieldCommand(t, self.field_payload(step, f)) for t, f in self.fields(step, timing)]
        cmds += load_commands(step, duration, base)
        cmds.append(EndCommand(duration))
        return cmds, duration


def bode_figure(result: Any, plt: Any, amplitude_label: str, note: str,
                beside: tuple[str, str] | None = None) -> Any:  # fmt: skip
    """A two-panel Bode plot of a sine step's result (per axis, amplitude and phase with their
    1-sigma against frequency, log scale); ``beside``: a second pair of values per point drawn
    dotted (the cage's own); ``note`` ends the frequency axis's label."""
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7.0, 5.0), sharex=True)
    panels = ((top, "amplitude", "amplitude_sigma"), (bottom, "phase_deg", "phase_sigma_deg"))
    for axis, points in result["axes"].items():
        f = [p["f_hz"] for p in points]
        for k, (ax, value, sigma) in enumerate(panels):
            ax.errorbar(f, [p[value] for p in points], yerr=[p[sigma] for p in points],
                        fmt="o-", ms=3, label=axis)  # fmt: skip
            if beside is not None:
                ax.plot(f, [p[beside[k]] for p in points], ":", color="0.5", lw=0.8)
    top.set_xscale("log")
    top.set_ylabel(amplitude_label)
    bottom.set_ylabel("phase (deg)")
    bottom.set_xlabel(f"frequency (Hz); dotted: {note}")
    for ax in (top, bottom):
        ax.grid(alpha=0.3, which="both")
    top.legend(fontsize=7)
    return fig
