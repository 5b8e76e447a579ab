"""Holding a field until its data suffice (issue 54): a step kind that needs settled samples at
each held field (:meth:`rig.steps.base.StepKind.settled_need`) gets them before the next field,
however late a busy computer or a slow link delivers them; the timeline after it moves on by as
much. Only a field still short after :data:`MAX_EXTRA_HOLD_S` is let go, and the step then says why
its analysis has too few points.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import timebase
from rig.engine.sampling import SensorSampler
from rig.steps.base import MAX_EXTRA_HOLD_S, SettledNeed

POLL_S = 0.05
"""How often a held field looks for its samples (s of the run's clock)."""


@dataclass
class HeldLonger:
    """What the gate added over one step: fields held longer, the longest extra hold and the sum
    (s), and the fields let go still short (with the first one's shortfall, for the message)."""

    fields: int = 0
    longest_s: float = 0.0
    total_s: float = 0.0
    short: int = 0
    first_short: str = ""

    def summary(self, step_number: int) -> tuple[str, str] | None:
        """(level, message) for the run's log, or None when nothing was held longer."""
        if self.fields == 0:
            return None
        text = (f"step {step_number}: {self.fields} field(s) held longer for their settled samples"
                f" (at most {self.longest_s:.2f} s, {self.total_s:.1f} s in all): the samples came"
                " late (a busy computer or a slow sensor)")  # fmt: skip
        if self.short:
            text += (f"; {self.short} still short after {MAX_EXTRA_HOLD_S:g} s more"
                     f" ({self.first_short})")  # fmt: skip
            return "warning", text
        return ("warning" if self.longest_s > 1.0 else "info"), text


class PointGate:
    """The settled samples of the field being held, counted from the samplers."""

    def __init__(self, need: SettledNeed, samplers: Mapping[str, SensorSampler]) -> None:
        self.need = need
        self.samplers = {d: samplers[d] for d in need.devices if d in samplers}
        self.held = HeldLonger()
        self._settled_from: float | None = None  # monotonic s: the open field's settled start
        self._plan_t = 0.0  # the open field's time in the plan (s from the step's start)

    def opened(self, reached_s: float, plan_t_s: float) -> None:
        """A field was reached at ``reached_s`` (monotonic s); its plan time ``plan_t_s``."""
        self._settled_from = reached_s + self.need.settle_s
        self._plan_t = plan_t_s

    def due_before(self, plan_t_s: float) -> bool:
        """A command at plan time ``plan_t_s`` ends the open field's hold."""
        return self._settled_from is not None and plan_t_s > self._plan_t

    def missing(self, now_s: float) -> dict[str, int]:
        """Per device, the settled samples the open field has so far, where short of the need."""
        assert self._settled_from is not None
        counts = {d: s.dated_within(self._settled_from, now_s, self.need.samples)
                  for d, s in self.samplers.items()}  # fmt: skip
        return {d: n for d, n in counts.items() if n < self.need.samples}

    def hold(self, wait: Callable[[float], float], stopped: Callable[[], bool]) -> float:
        """Hold the open field until its samples are in, :data:`MAX_EXTRA_HOLD_S` has passed or
        ``stopped()``; ``wait(t)`` waits until monotonic ``t`` (pauses, faults and aborts as the
        schedule's) and returns the time pauses added. Returns the hold's length (s)."""
        start = timebase.monotonic()
        paused = 0.0
        short = self.missing(start)
        if not short or stopped():
            self._settled_from = None
            return 0.0
        while short and not stopped():
            now = timebase.monotonic()
            if now - start - paused >= MAX_EXTRA_HOLD_S:
                self.held.short += 1
                if not self.held.first_short:
                    self.held.first_short = ", ".join(
                        f"{d} {n} of {self.need.samples}" for d, n in short.items()
                    )
                break
            paused += wait(now + POLL_S)
            short = self.missing(timebase.monotonic())
        self._settled_from = None
        took = timebase.monotonic() - start
        self.held.fields += 1
        self.held.longest_s = max(self.held.longest_s, took - paused)
        self.held.total_s += took - paused
        return took
