"""Carrying out one step on time: its field and load set-points at their times in the step, its
kind's own commands through its ``StepExecution``, pauses held and faults raised at every wait.
On the process's clock (:mod:`timebase`): in simulated time a step's timeline is simulated time."""

from __future__ import annotations

import threading
from array import array
from collections.abc import Callable, Sequence

import timebase
from rig.engine.commands import Commands
from rig.engine.point_gate import PointGate
from rig.engine.run_tracker import RunTracker, StepNow
from rig.engine.sampling import SensorSampler
from rig.engine.session import RigSession
from rig.procedure.plan import StepPlan
from rig.steps import KINDS
from rig.steps.base import RunContext, StepExecution
from rig.steps.vocabulary import ActionCommand, Command, FieldCommand, LoadCommand
from rig.store.run_store import RunWriter

CATCH_UP_S = 2.0
"""Longest wait at the end of a step for each sensor's samples up to that moment (s): they may sit
in a buffer while a busy computer runs something else (a null step's noise floor was once judged
on 3 of its 14 samples)."""
TRACK_SPACING_TOLERANCE = 0.1
"""A tracked set-point (an orbit replay's field and currents) is never sent sooner after the
previous one than their planned spacing less this fraction of it: a timeline held back by a busy
computer slips instead of catching up in a burst (which moves the field faster than the
reference's samples resolve and left half an orbit replay unusable, issue 30); the fraction
absorbs the scheduler's ordinary wake-up jitter."""


class StepScheduler:
    """Carries out the steps of one run, one at a time (:meth:`execute`)."""

    def __init__(self, rig: RigSession, writer: RunWriter, tracker: RunTracker,
                 commands: Commands, samplers: dict[str, SensorSampler], n_steps: int,
                 event: Callable[[str, str], None]) -> None:  # fmt: skip
        self.rig = rig
        self.writer = writer
        self.tracker = tracker
        self.commands = commands
        self.samplers = samplers
        self.n_steps = n_steps
        self.event = event
        self.lateness_s = array("d")  # 8 bytes per command: a 10 h run at 50 Hz keeps 14 MB

    def wait_until(self, t_target: float, stop: threading.Event | None = None) -> float:
        """Sleep until ``t_target`` (monotonic) or until ``stop`` is set, holding while a pause
        is asked for; returns the time shift added by pauses. A fault or an abort raises."""
        shift = 0.0
        while True:
            self.rig.check()  # a fault or an abort ends the wait
            if stop is not None and stop.is_set():
                return shift
            if self.tracker.pause_requested.is_set():
                shift += self._hold()
                continue
            remaining = t_target + shift - timebase.monotonic()
            if remaining <= 0:
                return shift
            # faults, aborts, pauses and the stop end the wait when they come
            wake = (*self.rig.interrupts, self.tracker.pause_requested)
            timebase.wait_any(wake if stop is None else (*wake, stop), remaining)

    def _hold(self) -> float:
        """Hold the schedule while the pause is asked for; returns how long it held (s)."""
        t_pause = timebase.monotonic()
        self.event("operator", "paused")
        tracker = self.tracker
        with tracker.paused():
            while tracker.pause_requested.is_set() and not tracker.abort_requested.is_set():
                self.rig.sleep(0.05)
        self.event("operator", "resumed")
        return timebase.monotonic() - t_pause

    def execute(self, plan: StepPlan, ctx: RunContext) -> None:
        """Carry out one step: its field and load set-points on time, its own action through its
        kind (rig.steps), which also decides what happens before and after."""
        step = plan.step
        t0 = timebase.monotonic()
        self.tracker.step = StepNow(step.index, step.name, t0, plan.duration_s)
        self.writer.set_step(step.index, step.name, step.kind, t0, None)
        self.event("info", f"step {step.index + 1}/{self.n_steps}: {step.name}")
        execution = KINDS[step.kind].execution(ctx, step)
        try:
            self._timeline(plan, execution, t0, self._gate(plan, ctx))
            execution.wind_down()
        except BaseException:
            execution.abort()
            self.rig.on_close(execution.after_safe)  # after the safe state (last in, first out)
            raise
        t_end = timebase.monotonic()
        self.writer.set_step(step.index, step.name, step.kind, t0, t_end)
        # the step's data are all in before it is judged
        for sampler in list(self.samplers.values()):
            sampler.caught_up(t_end, CATCH_UP_S)
        execution.finish(t0, t_end)

    def _gate(self, plan: StepPlan, ctx: RunContext) -> PointGate | None:
        """The gate holding each field of the step until its settled samples are in, if its kind
        needs them (:meth:`rig.steps.base.StepKind.settled_need`)."""
        kind = KINDS[plan.step.kind]
        need = kind.settled_need(plan.step, ctx.proc.magnetometers)
        return PointGate(need, self.samplers) if need is not None and kind.hold_from_field else None

    def _timeline(self, plan: StepPlan, execution: StepExecution, t0: float,
                  gate: PointGate | None) -> None:  # fmt: skip
        """Each command of the step at its time from ``t0`` (moved on by pauses, by a field
        step's set-point once its field is there, and by the time the step's own actions take)."""
        step, stop = plan.step, execution.stop
        hold_from_field = KINDS[step.kind].hold_from_field
        pace = TrackPace()
        keeping = KeptTime(plan.commands)
        for i, cmd in enumerate(plan.commands):
            setpoint = cmd if isinstance(cmd, FieldCommand | LoadCommand) else None
            track = setpoint is not None and bool(setpoint.payload.get("track"))
            keep_time = isinstance(cmd, FieldCommand) and bool(cmd.payload.get("keep_time"))
            t0 = pace.slipped(t0, cmd.t_s, track and not keep_time)
            t0 += self.wait_until(t0 + cmd.t_s, stop)
            if keep_time and keeping.overtaken(i, timebase.monotonic() - t0):
                continue  # its successor is due already: the sine keeps its time
            if gate is not None and gate.due_before(cmd.t_s):
                # the field before has its settled samples (or waited its most) before this
                t0 += gate.hold(
                    lambda t: self.wait_until(t, stop), lambda: stop is not None and stop.is_set()
                )
            if stop is not None and stop.is_set():
                break
            now = timebase.monotonic()
            pace.issued(cmd.t_s, now, track)
            if setpoint is not None:
                self.lateness_s.append(now - (t0 + cmd.t_s))
                # logged with when it was due (the timeline slipped) and its time in the plan (s
                # from the step's start): analysis judges a tracked timeline's spacing by the plan
                due = {"t_due": t0 + cmd.t_s, "t_plan": cmd.t_s}
                self.commands.command(step.index, setpoint, now, due)
                if isinstance(setpoint, FieldCommand) and hold_from_field and not track:
                    # its dwell starts once the field is there; a tracked set-point keeps the
                    # schedule (re-anchored on each, a sine's 4 ms writes stretched it by 11 %)
                    t0 = timebase.monotonic() - cmd.t_s
                    if gate is not None:
                        gate.opened(t0 + cmd.t_s, cmd.t_s)
            elif isinstance(cmd, ActionCommand):
                execution.run(cmd.payload)
                # what follows the step's own action (a set/reset pulse: the hold after it)
                # keeps its planned time however long the action took
                t0 += timebase.monotonic() - now
        if keeping.skipped:
            self.event("warning" if keeping.skipped > 1 else "info",
                       f"step {step.index + 1}: {keeping.skipped} of {keeping.total} sine set-points"
                       " skipped, each due when the next one was (the computer was busy); the"
                       " sines kept their time")  # fmt: skip
        held = gate.held.summary(step.index + 1) if gate is not None else None
        if held is not None:
            self.event(*held)
        if pace.slip_s > 0.0:
            self.event("warning" if pace.slip_s > 1.0 else "info",
                       f"step {step.index + 1}: its tracked set-points ran {pace.slip_s:.2f} s behind"
                       " the plan (the computer was busy); each kept its planned spacing, none was"
                       " sent in a burst")  # fmt: skip


class TrackPace:
    """The pace of a step's tracked set-points: each group (the commands at one plan time) at
    least its planned spacing after the previous group was issued, less
    :data:`TRACK_SPACING_TOLERANCE` of it; what that adds is the timeline's slip (s)."""

    def __init__(self) -> None:
        self.slip_s = 0.0
        self._last: tuple[float, float] | None = None  # (plan time s, issued monotonic s)

    def slipped(self, t0: float, t_s: float, track: bool) -> float:
        """The step's start ``t0`` (monotonic s), moved on so that a tracked command at plan time
        ``t_s`` is not due sooner than its spacing after the previous group allows."""
        if not track or self._last is None or t_s <= self._last[0]:
            return t0
        spacing = t_s - self._last[0]
        earliest = self._last[1] + (1.0 - TRACK_SPACING_TOLERANCE) * spacing
        if t0 + t_s >= earliest:
            return t0
        # late: the rest of the timeline moves on by as much, so nothing catches up later
        shift = self._last[1] + spacing - (t0 + t_s)
        self.slip_s += shift
        return t0 + shift

    def issued(self, t_s: float, now: float, track: bool) -> None:
        """A command at plan time ``t_s`` was issued at ``now``; a group starts with its first."""
        if track and (self._last is None or t_s > self._last[0]):
            self._last = (t_s, now)


class KeptTime:
    """The commands that keep their time (``keep_time``: a sine's set-points): one whose
    successor is already due when it could be sent is skipped, never sent late nor slipped (a
    sine stretched in time is no longer a sine at its frequency, issue 54)."""

    def __init__(self, commands: Sequence[Command]) -> None:
        self.next_t_s: dict[int, float] = {}
        self.total = 0
        self.skipped = 0
        later: float | None = None
        for i in range(len(commands) - 1, -1, -1):
            cmd = commands[i]
            if isinstance(cmd, FieldCommand) and cmd.payload.get("keep_time"):
                self.total += 1
                if later is not None and later > cmd.t_s:
                    self.next_t_s[i] = later
                later = cmd.t_s

    def overtaken(self, index: int, now_plan_s: float) -> bool:
        """Whether command ``index`` is to be skipped at ``now_plan_s`` (s from the step's start
        on its timeline): its successor is due already."""
        if now_plan_s < self.next_t_s.get(index, float("inf")):
            return False
        self.skipped += 1
        return True
