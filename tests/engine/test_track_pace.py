"""A tracked timeline held back by a busy computer slips; it never catches up in a burst."""

from __future__ import annotations

import itertools

import pytest

from rig.engine.schedule import TRACK_SPACING_TOLERANCE, TrackPace

SPACING_S = 0.05


def _run(
    delays_s: dict[int, float], n: int = 20, jitter_s: float = 0.0
) -> tuple[list[float], TrackPace]:
    """Issue ``n`` tracked groups (a field and a load at each plan time); group ``k`` is issued
    ``delays_s[k]`` after it fell due (a stall), the rest ``jitter_s`` late. Returns the issue
    times and the pace."""
    pace, t0, issued = TrackPace(), 100.0, []
    for k in range(n):
        t_s = k * SPACING_S
        for _ in ("field", "load"):
            t0 = pace.slipped(t0, t_s, True)
            now = t0 + t_s + delays_s.get(k, jitter_s)
            pace.issued(t_s, now, True)
        issued.append(now)
    return issued, pace


def test_on_time_timeline_is_not_moved() -> None:
    issued, pace = _run({}, jitter_s=0.001)
    assert pace.slip_s == 0.0
    assert issued[-1] == pytest.approx(100.0 + 19 * SPACING_S + 0.001)


def test_a_stall_slips_the_rest_instead_of_a_burst() -> None:
    issued, pace = _run({5: 0.3})
    gaps = [b - a for a, b in itertools.pairwise(issued)]
    # after the stall every set-point keeps its planned spacing: none sent sooner
    assert min(gaps) >= (1.0 - TRACK_SPACING_TOLERANCE) * SPACING_S - 1e-9
    assert gaps[5:] == pytest.approx([SPACING_S] * len(gaps[5:]))
    assert pace.slip_s == pytest.approx(0.3)


def test_repeated_stalls_add_up() -> None:
    _, pace = _run({3: 0.2, 9: 0.12, 15: 0.5})
    assert pace.slip_s == pytest.approx(0.82)


def test_untracked_commands_are_not_paced() -> None:
    pace = TrackPace()
    pace.issued(0.0, 100.5, True)  # a tracked set-point issued late
    assert pace.slipped(100.0, 0.05, False) == 100.0
