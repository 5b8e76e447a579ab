"""Bursts on a tracked timeline (an orbit replay's set-points and loads) found from the record
(issue 30): a computer that held the timeline back and then caught up moved the field faster
than the reference resolves, and those DUT samples are left out; a timeline that is only late,
steadily or more and more (a slow supply link), leaves nothing out; a run that was mostly bursts
is a timing fault, never a verdict."""

from __future__ import annotations

from pathlib import Path

import pytest

from rig.analysis import late_intervals, late_timeline_fault
from rig.store import RunReader
from rig.store.run_store import RunWriter

PERIOD_S = 0.05


def _record(folder: Path, issued: list[float], *, kind: str = "field") -> RunReader:
    """A run whose tracked commands were due every 50 ms from t = 100 s and issued at ``issued``
    (each done 2 ms later)."""
    w = RunWriter(folder)
    for i, t_issued in enumerate(issued):
        payload = {"track": True, "t_due": 100.0 + PERIOD_S * i, "t_issued": t_issued}
        if kind == "load":
            payload |= {"channel": "load_bus", "current_a": 0.1 * i}
        else:
            payload |= {"field_ut": [10.0 + i, 0.0, 0.0], "ramped": False}
        w.add_command(t_issued + 0.002, 0, kind, payload)
    w.close("complete", "")
    return RunReader(folder)


def test_a_stall_then_a_burst_is_found_and_only_the_burst(tmp_path: Path) -> None:
    on_time = [100.0 + PERIOD_S * i for i in range(10)]
    # commands 10-14 held back by a 0.3 s stall, then sent 2 ms apart; 15 on its time again
    burst = [100.0 + PERIOD_S * 14 + 0.002 * k for k in range(5)]
    after = [100.0 + PERIOD_S * i for i in range(15, 20)]
    reader = _record(tmp_path, on_time + burst + after)
    try:
        found = late_intervals(reader, 0.6 * PERIOD_S)
    finally:
        reader.close()
    # 11-14 each came 48 ms sooner than planned after their predecessor; 10 (the held one) and
    # 15 (on time after the burst) did not
    assert found.shape == (4, 2)
    assert found[0, 0] == pytest.approx(burst[0])
    assert found[-1, 1] == pytest.approx(burst[-1] + 0.002)


@pytest.mark.parametrize("lateness_per_command_s", [0.0, 0.02, 0.045])
def test_a_timeline_late_steadily_or_more_and_more_leaves_nothing_out(
    tmp_path: Path, lateness_per_command_s: float
) -> None:
    # 0.045 s per command: a supply link that answers each set-point 95 ms after it was sent
    issued = [100.0 + 0.3 + (PERIOD_S + lateness_per_command_s) * i for i in range(30)]
    reader = _record(tmp_path, issued, kind="load")
    try:
        assert late_intervals(reader, 0.6 * PERIOD_S).size == 0
    finally:
        reader.close()


def test_a_run_recorded_before_due_times_has_no_bursts(tmp_path: Path) -> None:
    w = RunWriter(tmp_path)
    for i in range(5):
        w.add_command(100.0 + 0.002 * i, 0, "field", {"track": True, "t_issued": 100.0 + 0.002 * i})
    w.close("complete", "")
    reader = RunReader(tmp_path)
    try:
        assert late_intervals(reader, 0.03).size == 0
    finally:
        reader.close()


def test_mostly_bursts_is_a_timing_fault_a_few_are_not() -> None:
    assert late_timeline_fault(40, 100) is None
    fault = late_timeline_fault(60, 100)
    assert fault is not None and fault.startswith("timing fault: 60 of 100 DUT samples")
    assert "re-run the step on a less busy computer" in fault
