"""A simulated clock's threads on one CPU (timebase.one_cpu): confined inside, given back after."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import timebase
from timebase.one_cpu import ENV, chosen_cpu, running_cpu

pytestmark = pytest.mark.skipif(
    not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2,
    reason="needs a system that confines threads, and two CPUs",
)


def test_the_clock_and_the_threads_it_starts_run_on_one_cpu_then_get_their_cpus_back(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv(ENV, raising=False)
    before = os.sched_getaffinity(0)
    seen: list[set[int]] = []
    with timebase.simulated(stall_report_s=None):
        inside = os.sched_getaffinity(0)
        t = timebase.Thread(lambda: seen.append(os.sched_getaffinity(0)), name="p")
        t.start()
        t.join()
        assert running_cpu() in inside
    assert len(inside) == 1 and inside <= before
    assert seen == [inside]
    assert os.sched_getaffinity(0) == before


def test_any_leaves_the_cpus_and_a_number_chooses_one(monkeypatch: pytest.MonkeyPatch) -> None:
    before = os.sched_getaffinity(0)
    monkeypatch.setenv(ENV, "any")
    with timebase.simulated(stall_report_s=None):
        assert os.sched_getaffinity(0) == before
    last = max(before)
    monkeypatch.setenv(ENV, str(last))
    with timebase.simulated(stall_report_s=None):
        assert os.sched_getaffinity(0) == {last}
    assert chosen_cpu({0, 1}) in (None, last)


def test_a_wrong_choice_says_what_to_give(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ENV, "fast")
    with pytest.raises(ValueError, match=r"TIMEBASE_CPU='fast': give a CPU number .* or 'any'"):
        chosen_cpu({0, 1})
    monkeypatch.setenv(ENV, "4096")
    assert chosen_cpu({0, 1}) is None  # not one of the allowed: left as they were


def test_two_simulations_at_once_take_two_cpus(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Each claims its CPU (a lock file): the second takes another though both run on the same.
    The claims in a folder of this test's own: another test worker's simulation holding a CPU
    left both on one (seen once in a full run)."""
    import threading

    from timebase import one_cpu as module

    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.setattr(module.tempfile, "gettempdir", lambda: str(tmp_path))
    first = min(os.sched_getaffinity(0))
    monkeypatch.setattr(module, "running_cpu", lambda: first)
    taken: list[int | None] = []
    inside, leave = threading.Barrier(3), threading.Event()

    def simulation() -> None:
        with module.one_cpu() as cpu:
            taken.append(cpu)
            inside.wait(10.0)
            leave.wait(10.0)

    threads = [threading.Thread(target=simulation) for _ in range(2)]
    for t in threads:
        t.start()
    inside.wait(10.0)  # both inside at once
    leave.set()
    for t in threads:
        t.join(10.0)
    assert sorted(taken, key=str)[0] is not None and len(set(taken)) == 2
    assert first in taken
