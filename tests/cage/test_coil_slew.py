"""The ramp planner bounds the coil current's own slope, not only its set-points' average (issue
51): 0.5 A set-point steps every 50 ms (10 A/s on average) into the simulated coils' 25 ms L/R
peaked at 18-26 A/s. With ``[cage] coil_tau_s`` the steps are sized so that the peak right after
each one is the slew limit: checked on a first-order coil here, and on the simulated cage's true
coil current over real Modbus."""

from __future__ import annotations

import math
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest

import timebase
from rig.cage.limits import CageLimits, plan_ramp
from rig.config import load_rig_config
from rig.devices import build_cage
from sim.cage import SimulatedCage
from tests.simcage import sim_cage

pytestmark = pytest.mark.simcage

SLEW = 10.0
TAU_S = 0.025


def peak_slope_a_per_s(points: list[np.ndarray], step_s: float, tau_s: float) -> float:
    """The largest slope of a first-order coil (L/R ``tau_s``) driven by the set-points, one
    every ``step_s``, evaluated exactly just after each step (where it is largest)."""
    current, peak = np.zeros(3), 0.0
    for p in points:
        peak = max(peak, float(np.max(np.abs(p - current))) / tau_s)
        current = p + (current - p) * math.exp(-step_s / tau_s)
    return peak


def test_the_steps_into_the_coils_l_over_r_keep_the_slope_within_the_limit() -> None:
    ideal = CageLimits((2.5, 2.5, 2.5), 120.0, SLEW, 0.05)
    bound = CageLimits((2.5, 2.5, 2.5), 120.0, SLEW, 0.05, coil_tau_s=TAU_S)
    target = np.array([2.0, -1.0, 0.5])
    assert peak_slope_a_per_s(plan_ramp(np.zeros(3), target, ideal), 0.05, TAU_S) > 18.0
    points = plan_ramp(np.zeros(3), target, bound)
    assert peak_slope_a_per_s(points, 0.05, TAU_S) <= SLEW * (1 + 1e-9)
    np.testing.assert_allclose(points[-1], target)
    # a shorter L/R is the harder coil: steps sized for the shortest hold for every longer one
    assert peak_slope_a_per_s(points, 0.05, 2 * TAU_S) <= SLEW
    assert bound.max_step_a == pytest.approx(SLEW * TAU_S * (1 - math.exp(-2.0)))


def test_on_the_simulated_cage_the_true_coil_current_keeps_the_slew(tmp_path: Path) -> None:
    """The simulated rig's configuration states its coils' L/R (25 ms): a ramp of coil z to
    2 A and back is watched in the simulator's truth every 1 ms."""
    with sim_cage(tmp_path) as (cage, rig_toml):
        cage_cfg = load_rig_config(rig_toml).cage
        assert cage_cfg is not None and cage_cfg.coil_tau_s == pytest.approx(0.025, rel=0.01)
        samples = ramp_watched(cage, rig_toml)
    t, i = np.array(samples).T
    slope = np.abs(np.diff(i) / np.diff(t))
    assert i.max() > 1.9, i.max()
    # the slope over each ~1 ms interval (the watcher's own lateness only lengthens intervals)
    assert slope.max() <= SLEW * 1.05, slope.max()


def ramp_watched(cage: SimulatedCage, rig_toml: Path) -> list[tuple[float, float]]:
    """Coil z ramped to 2 A and back through the controller; (time s, true current A) every
    1 ms meanwhile."""
    cfg = load_rig_config(rig_toml)
    physics = cage.physics
    samples: list[tuple[float, float]] = []
    stop = timebase.Event()

    def watch() -> None:
        while not stop.wait(0.001):
            t = timebase.monotonic()
            samples.append((t, float(physics.true_coil_currents(t)[2])))

    watcher = timebase.Thread(watch, name="truth-watch", daemon=True)
    watcher.start()
    try:
        with ExitStack() as stack:
            controller = build_cage(cfg, stack, cage.i2c_bus)
            controller.set_currents([0.0, 0.0, 2.0])
            controller.set_currents([0.0, 0.0, 0.0])
    finally:
        stop.set()
        watcher.join(1.0)
    return samples
