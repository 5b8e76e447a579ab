"""Property tests: no command sequence yields a set-point beyond a limit or a step above the slew."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import timebase
from rig.cage.controller import AxisDrive, CageController
from rig.cage.limits import CageLimitError, CageLimits, plan_ramp
from rig.cage.model import CageModel

LIMITS = CageLimits((1.5, 1.2, 2.0), max_field_ut=120.0, max_slew_a_per_s=4.0, step_s=0.05)
currents = st.tuples(*(st.floats(-2.5, 2.5, allow_nan=False) for _ in range(3)))


def within(i: np.ndarray) -> bool:
    return bool(np.all(np.abs(i) <= np.array(LIMITS.max_current_a) + 1e-12))


@settings(max_examples=400, deadline=None)
@given(st.lists(currents, min_size=1, max_size=6))
def test_plan_ramp_never_exceeds_limits_or_slew(targets: list[tuple[float, float, float]]) -> None:
    here = np.zeros(3)
    for target in targets:
        t = np.array(target)
        if not within(t):
            with pytest.raises(CageLimitError):
                plan_ramp(here, t, LIMITS)
            continue
        points = plan_ramp(here, t, LIMITS)
        prev = here
        for p in points:
            assert within(p)
            assert np.all(np.abs(p - prev) <= LIMITS.max_step_a + 1e-12)
            assert not np.any(np.sign(p) * np.sign(prev) < 0), "sign change without passing zero"
            prev = p
        if points:
            np.testing.assert_allclose(points[-1], t, atol=1e-12)
        here = t


class RecordingSupply:
    """A driver-level double that records every set-point and checks the driver's own range."""

    def __init__(self, max_a: float, bipolar: bool) -> None:
        self.max_a, self.bipolar = max_a, bipolar
        self.history: list[float] = []
        self.on = False

    def set_voltage(self, volts: float) -> float:
        return volts

    def set_current(self, amps: float) -> float:
        assert (-self.max_a if self.bipolar else 0.0) <= amps <= self.max_a
        self.history.append(amps)
        return amps

    def set_output(self, on: bool) -> None:
        self.on = on

    def safe(self) -> None:
        self.on = False
        self.history.append(0.0)


class RecordingRelays:
    def __init__(self, supplies: list[RecordingSupply]) -> None:
        self.supplies = supplies
        self.flips = 0

    def set_polarity(self, axis: int, sign: int) -> None:
        assert self.supplies[axis].history[-1] == 0.0, "relay switched with current flowing"
        self.flips += 1


fields = st.tuples(*(st.floats(-90.0, 90.0, allow_nan=False) for _ in range(3)))


@settings(max_examples=150, deadline=None)
@given(st.lists(fields, min_size=1, max_size=5), st.booleans())
def test_controller_field_commands_stay_within_limits(
    commands: list[tuple[float, float, float]], bipolar: bool
) -> None:
    with timebase.simulated(stall_report_s=None):  # the ramp down's own waits: no wall time
        _command_and_check(commands, bipolar)


def _command_and_check(commands: list[tuple[float, float, float]], bipolar: bool) -> None:
    supplies = [RecordingSupply(m, bipolar) for m in LIMITS.max_current_a]
    relays = None if bipolar else RecordingRelays(supplies)
    model = CageModel(
        np.array([[40.0, 0.8, -0.4], [0.6, 39.0, 0.4], [-0.3, 0.7, 41.0]]),
        np.array([19.6, 1.2, -44.8]),
    )
    ctl = CageController([AxisDrive(s, bipolar, 12.0) for s in supplies], model, LIMITS, relays=relays,
                         sleep=lambda s: None)  # fmt: skip
    for field in commands:
        before = len(ctl.sent)
        try:
            ctl.set_field(field)
        except CageLimitError:
            assert len(ctl.sent) == before, "a refused command must send nothing"
    ctl.safe()
    prev = np.zeros(3)
    for point in ctl.sent:
        assert within(point)
        assert np.all(np.abs(point - prev) <= LIMITS.max_step_a + 1e-12)
        prev = point
    assert np.allclose(ctl.sent[-1] if ctl.sent else np.zeros(3), 0.0)
    assert not any(s.on for s in supplies)
