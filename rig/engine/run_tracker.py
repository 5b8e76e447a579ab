"""The state of the run being carried out, as the live view and the page read it.

One object, written by the main thread (state, step) and by the operator's channels (pause,
abort requests from signals and the page), read by any thread. Its state moves only along the
table of :mod:`rig.store.run_states`; a move not in it raises ``RunStateError``. Its events are the
clock's (:mod:`timebase`): a thread outside a simulated clock (the page's) may set them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

import timebase
from rig.store.run_states import RunStatus, check_transition


@dataclass(frozen=True)
class StepNow:
    """The step being carried out."""

    index: int
    name: str
    t_start: float
    """Monotonic s its timeline started (moved on by pauses and by fields that took long)."""
    duration_s: float
    """Nominal."""


class RunTracker:
    """The run's state, the operator's requests and the step under way."""

    def __init__(self) -> None:
        self.state = RunStatus.RUNNING
        self.pause_requested = timebase.Event()
        """Set by the operator (SIGUSR1, the page); the schedule holds at its next wait."""
        self.abort_requested = timebase.Event()
        """Set by the operator (the page); the session raises ``RunAborted`` at its next wait."""
        self.abort_reason: str | None = None
        self.step: StepNow | None = None
        self._lock = timebase.Lock()

    def to(self, new: RunStatus) -> None:
        """Move to ``new``; raises ``RunStateError`` if the table does not allow it."""
        with self._lock:
            self.state = check_transition(self.state, new)

    @property
    def holding(self) -> bool:
        """Paused: the schedule is held."""
        return self.state is RunStatus.PAUSED

    def toggle_pause(self) -> None:
        """Ask for a pause, or for the end of one (SIGUSR1)."""
        if self.pause_requested.is_set():
            self.pause_requested.clear()
        else:
            self.pause_requested.set()

    def request_abort(self, reason: str) -> None:
        """Ask for the run to end through the safe path; the first reason is kept."""
        if self.abort_reason is None:
            self.abort_reason = reason
        self.abort_requested.set()

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """Inside, the run is PAUSED; back to RUNNING on the way out, whatever ended the pause."""
        self.to(RunStatus.PAUSED)
        try:
            yield
        finally:
            self.to(RunStatus.RUNNING)
