"""Carrying out one step on time: its field and load set-points at their times in the step, its
kind's own commands through its ``StepExecution``, pauses held and faults raised at every wait."""

from __future__ import annotations

import threading
import time
from array import array
from collections.abc import Callable

from rig.engine.commands import Commands
from rig.engine.run_tracker import RunTracker, StepNow
from rig.engine.sampling import SensorSampler
from rig.engine.session import RigSession
from rig.procedure.plan import StepPlan
from rig.steps import KINDS
from rig.steps.base import RunContext, StepExecution
from rig.store.run_store import RunWriter

CATCH_UP_S = 2.0
"""Longest wait at the end of a step for each sensor's samples up to that moment (s): they may sit
in a buffer while a busy computer runs something else (a null step's noise floor was once judged
on 3 of its 14 samples)."""


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
            remaining = t_target + shift - time.monotonic()
            if remaining <= 0:
                return shift
            time.sleep(min(remaining, 0.05))

    def _hold(self) -> float:
        """Hold the schedule while the pause is asked for; returns how long it held (s)."""
        t_pause = time.monotonic()
        self.event("operator", "paused")
        tracker = self.tracker
        with tracker.paused():
            while tracker.pause_requested.is_set() and not tracker.abort_requested.is_set():
                self.rig.sleep(0.05)
        self.event("operator", "resumed")
        return time.monotonic() - t_pause

    def execute(self, plan: StepPlan, ctx: RunContext) -> None:
        """Carry out one step: its field and load set-points on time, its own action through its
        kind (rig.steps), which also decides what happens before and after."""
        step = plan.step
        t0 = time.monotonic()
        self.tracker.step = StepNow(step.index, step.name, t0, plan.duration_s)
        self.writer.set_step(step.index, step.name, step.kind, t0, None)
        self.event("info", f"step {step.index + 1}/{self.n_steps}: {step.name}")
        execution = KINDS[step.kind].execution(ctx, step)
        try:
            self._timeline(plan, execution, t0)
            execution.wind_down()
        except BaseException:
            execution.abort()
            raise
        t_end = time.monotonic()
        self.writer.set_step(step.index, step.name, step.kind, t0, t_end)
        # the step's data are all in before it is judged
        for sampler in list(self.samplers.values()):
            sampler.caught_up(t_end, CATCH_UP_S)
        execution.finish(t0, t_end)

    def _timeline(self, plan: StepPlan, execution: StepExecution, t0: float) -> None:
        """Each command of the step at its time from ``t0`` (moved on by pauses, and by a field
        step's set-point once its field is there)."""
        step, stop = plan.step, execution.stop
        hold_from_field = KINDS[step.kind].hold_from_field
        for cmd in plan.commands:
            t0 += self.wait_until(t0 + cmd.t_s, stop)
            if stop is not None and stop.is_set():
                break
            now = time.monotonic()
            if cmd.kind in ("field", "load"):
                self.lateness_s.append(now - (t0 + cmd.t_s))
                # logged with when it was due: analysis leaves out what a late timeline moved
                due = {"t_due": t0 + cmd.t_s}
                self.commands.command(step.index, cmd.kind, cmd.payload | due, now)
                if cmd.kind == "field" and hold_from_field:
                    t0 = time.monotonic() - cmd.t_s  # its dwell starts once the field is there
            elif cmd.kind != "end":
                execution.run(cmd.payload)
