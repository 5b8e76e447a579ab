"""The run's state machine: one table of transitions, enums whose values are the stored strings."""

from __future__ import annotations

import json

import pytest

from rig.engine.run_tracker import RunTracker
from rig.store.run_states import (
    ENDED,
    TRANSITIONS,
    RunStateError,
    RunStatus,
    Verdict,
    check_transition,
    verdict_of,
)


def test_the_stored_strings_stay_the_same() -> None:
    assert [s.value for s in RunStatus] == [
        "running", "paused", "complete", "failed", "re-run", "aborted", "error", "incomplete"
    ]  # fmt: skip
    assert [v.value for v in Verdict] == ["PASS", "FAIL", "RE-RUN"]
    assert json.dumps({"status": RunStatus.ABORTED}) == '{"status": "aborted"}'


@pytest.mark.parametrize("verdict", list(Verdict))
def test_every_verdict_round_trips(verdict: Verdict) -> None:
    stored = json.loads(json.dumps({"overall": verdict}))["overall"]
    assert Verdict(stored) is verdict and verdict_of(stored) is verdict
    assert Verdict.RERUN == "RE-RUN"


def test_an_unknown_verdict_is_none_never_a_pass() -> None:
    assert verdict_of("MAYBE") is None and verdict_of(None) is None


def test_the_table_covers_every_state_and_ends_are_final() -> None:
    assert set(TRANSITIONS) == set(RunStatus)
    for end in ENDED:
        assert not TRANSITIONS[end]
        with pytest.raises(RunStateError):
            check_transition(end, RunStatus.RUNNING)
    assert check_transition(RunStatus.RUNNING, RunStatus.PAUSED) is RunStatus.PAUSED
    assert check_transition(RunStatus.PAUSED, RunStatus.ABORTED) is RunStatus.ABORTED
    with pytest.raises(RunStateError, match="from running to running"):
        check_transition(RunStatus.RUNNING, RunStatus.RUNNING)


def test_the_tracker_moves_only_along_the_table() -> None:
    tracker = RunTracker()
    assert tracker.state is RunStatus.RUNNING and not tracker.holding
    with tracker.paused():
        assert tracker.holding and tracker.state is RunStatus.PAUSED
    assert tracker.state is RunStatus.RUNNING
    tracker.to(RunStatus.ABORTED)
    with pytest.raises(RunStateError, match="from aborted to running"):
        tracker.to(RunStatus.RUNNING)
    assert tracker.state is RunStatus.ABORTED


def test_pause_and_abort_requests() -> None:
    tracker = RunTracker()
    tracker.toggle_pause()
    assert tracker.pause_requested.is_set()
    tracker.toggle_pause()
    assert not tracker.pause_requested.is_set()
    tracker.request_abort("aborted from the web page")
    tracker.request_abort("stopped by SIGTERM")
    assert tracker.abort_requested.is_set() and tracker.abort_reason == "aborted from the web page"
