"""The gate that holds a field until its settled samples are in (issue 54), on a simulated clock
with samplers that report what they were given."""

from __future__ import annotations

from typing import Any, cast

import pytest

import timebase
from rig.engine.point_gate import PointGate
from rig.steps.base import MAX_EXTRA_HOLD_S, SettledNeed


class Dated:
    """A sampler's count of dated samples: one sample every ``period_s`` from ``first_s``."""

    def __init__(self, first_s: float, period_s: float) -> None:
        self.first_s, self.period_s = first_s, period_s

    def dated_within(self, after_s: float, before_s: float, enough: int) -> int:
        n, t = 0, self.first_s
        while t < before_s and n < enough:
            n += after_s <= t
            t += self.period_s
        return n


def _wait(t_s: float) -> float:
    timebase.sleep(max(0.0, t_s - timebase.monotonic()))
    return 0.0  # no pause


def _gate(samplers: dict[str, Dated]) -> PointGate:
    return PointGate(SettledNeed(("dut", "reference"), 3, 0.25), cast(Any, samplers))


def test_a_field_with_its_samples_is_not_held() -> None:
    with timebase.simulated():
        gate = _gate({"dut": Dated(0.0, 0.01), "reference": Dated(0.0, 0.05)})
        gate.opened(timebase.monotonic(), 0.0)
        timebase.sleep(0.6)
        assert gate.due_before(0.6) and not gate.due_before(0.0)
        assert gate.hold(_wait, lambda: False) == 0.0
        assert gate.held.summary(1) is None and not gate.due_before(0.6)


def test_late_samples_hold_the_field_until_they_are_in() -> None:
    with timebase.simulated():
        # the reference's samples arrive only from 2 s on
        gate = _gate({"dut": Dated(0.0, 0.01), "reference": Dated(2.0, 0.05)})
        gate.opened(0.0, 0.0)
        timebase.sleep(0.6)
        took = gate.hold(_wait, lambda: False)
        assert took == pytest.approx(2.0 + 3 * 0.05 - 0.6, abs=0.06)
        level, text = gate.held.summary(4) or ("", "")
        assert level == "warning" and text.startswith("step 4: 1 field(s) held longer")


def test_a_field_short_after_the_most_is_let_go_and_named() -> None:
    with timebase.simulated():
        gate = _gate({"dut": Dated(0.0, 0.01), "reference": Dated(1e9, 0.05)})  # silent
        gate.opened(0.0, 0.0)
        timebase.sleep(0.6)
        took = gate.hold(_wait, lambda: False)
        assert took == pytest.approx(MAX_EXTRA_HOLD_S, abs=0.06)
        level, text = gate.held.summary(2) or ("", "")
        assert level == "warning" and "1 still short" in text and "reference 0 of 3" in text


def test_a_stopped_step_is_not_held() -> None:
    with timebase.simulated():
        gate = _gate({"dut": Dated(0.0, 0.01), "reference": Dated(1e9, 0.05)})
        gate.opened(0.0, 0.0)
        assert gate.hold(_wait, lambda: True) == 0.0
