"""A run's states, the transitions between them (one table) and the acceptance verdicts.

The values are the strings the run store, the lab index, the web page and the reports have always
used (``StrEnum``: a member is its string), so nothing stored changes. ``PAUSED`` is a state of the
run while it holds its schedule; it is never stored (the store says ``running`` meanwhile).
"""

from __future__ import annotations

from enum import StrEnum


class RunStatus(StrEnum):
    """What a run is doing, or how it ended."""

    RUNNING = "running"
    PAUSED = "paused"
    """Holding its schedule on the operator's request; stored as ``running``."""
    COMPLETE = "complete"
    """Every step done, and no acceptance check failed."""
    FAILED = "failed"
    """Every step done; an acceptance check failed."""
    RERUN = "re-run"
    """Every step done, but data a check judges failed the timing checks (ADR 0020): the DUT is
    judged neither way; the steps named in the verdict must be run again."""
    ABORTED = "aborted"
    """Ended by the operator (Ctrl-C, a signal, the page's abort)."""
    ERROR = "error"
    """Ended by a fault or an error."""
    INCOMPLETE = "incomplete"
    """Its recording process died without closing it (marked by the next reader)."""


class Verdict(StrEnum):
    """The overall acceptance verdict of a run, and of each criterion."""

    PASS = "PASS"
    FAIL = "FAIL"
    RERUN = "RE-RUN"
    """The run's timing checks failed: its data cannot judge the DUT either way; run it again."""


ENDED = (
    RunStatus.COMPLETE,
    RunStatus.FAILED,
    RunStatus.RERUN,
    RunStatus.ABORTED,
    RunStatus.ERROR,
    RunStatus.INCOMPLETE,
)
"""The states a run ends in (no transition leaves them)."""

TRANSITIONS: dict[RunStatus, frozenset[RunStatus]] = {
    RunStatus.RUNNING: frozenset({RunStatus.PAUSED, *ENDED}),
    RunStatus.PAUSED: frozenset({RunStatus.RUNNING, *ENDED}),
    **{state: frozenset() for state in ENDED},
}
"""Every allowed transition: the one table of the run's state machine."""

ACCEPTANCE = (RunStatus.COMPLETE, RunStatus.FAILED)
"""The ends whose verdict counts: every step was carried out."""

EXIT_CODES: dict[RunStatus, int] = {
    RunStatus.COMPLETE: 0,
    RunStatus.FAILED: 1,
    RunStatus.ERROR: 2,
    RunStatus.RERUN: 3,
    RunStatus.ABORTED: 130,
}
"""``rig run``'s exit code per end (any other: 2)."""


class RunStateError(RuntimeError):
    """A transition the table does not allow: a bug in the engine, never the operator's doing."""


def check_transition(old: RunStatus, new: RunStatus) -> RunStatus:
    """``new`` when the table allows ``old`` -> ``new``; else raise :class:`RunStateError`."""
    if new not in TRANSITIONS[old]:
        raise RunStateError(f"a run cannot go from {old} to {new}")
    return new


def verdict_of(value: object) -> Verdict | None:
    """The verdict named ``value`` (a stored string), or None for one this version does not know
    (a reader shows such a verdict as it is and never takes it for a pass)."""
    try:
        return Verdict(str(value))
    except ValueError:
        return None
