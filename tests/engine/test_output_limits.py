"""Limits belong to the outputs: a cage coil named as a load is refused by `rig check` and `rig
run`; forced past that check, the coil's own limits (the cage's) refuse the set-point that would
exceed them, on the simulated cage over real Modbus, and the field never passes the cage limit."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rig.engine.runner as runner_module
from rig.config import load_rig_config
from rig.devices import open_load
from rig.engine.runner import Runner
from rig.errors import UserInputError
from rig.output_limits import (
    OutputLimitError,
    cage_model,
    field_limit_current_a,
    output_limits,
)
from rig.procedure.language import parse_procedure
from sim.cage import SimulatedCage
from tests.simrun import run_watched

RIG = [sys.executable, "-m", "rig.cli"]
COIL_AS_LOAD = """procedure: Coil as a load
magnetometers: {dut: dut, reference: reference}
loads: [coil_x]
steps:
  - set_field: {field_ut: [0, 0, 0], hold_s: 4}
    loads:
      coil_x: {ramp: {from_a: 0.0, to_a: 5.0, step_s: 0.1}}
"""
"""The attack of issue 29: coil_x at up to 5 A as a load (the cage allows 2.5 A and 120 uT)."""


pytestmark = [pytest.mark.realtime, pytest.mark.usefixtures("own_lock_dir")]


@pytest.mark.parametrize(("device", "role"), [("coil_x", "x coil supply"), ("polarity", "polarity relays"),
                                              ("reference", "reference magnetometer"),
                                              ("trim_y", "y trim supply")])  # fmt: skip
def test_rig_check_refuses_a_cage_device_as_a_load(
    rig_toml: Path, tmp_path: Path, device: str, role: str
) -> None:
    proc = tmp_path / "p.yaml"
    proc.write_text(COIL_AS_LOAD.replace("coil_x", device))
    done = subprocess.run([*RIG, "check", str(proc), "--rig", str(rig_toml)], capture_output=True,
                          text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2, done
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert f"'{device}' is the cage's {role}" in lines[0]
    assert "name a load channel (load_bus, load_panel" in lines[0], lines[0]


def test_rig_run_refuses_it_before_any_output_is_written(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path
) -> None:
    proc = tmp_path / "p.yaml"
    proc.write_text(COIL_AS_LOAD)
    writes = {n: s.writes for n, s in cage.physics.supplies.items()}
    runs = tmp_path / "runs"
    runner = Runner(parse_procedure(proc), load_rig_config(rig_toml), runs, i2c_bus=cage.i2c_bus,
                    confirm=lambda s: True, live=False)  # fmt: skip
    with pytest.raises(UserInputError, match="'coil_x' is the cage's x coil supply"):
        runner.run()
    assert not runs.exists()
    assert {n: s.writes for n, s in cage.physics.supplies.items()} == writes
    done = subprocess.run([*RIG, "run", str(proc), "--rig", str(rig_toml), "--yes",
                           "--runs-dir", str(runs)], capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert not runs.exists()
    assert {n: s.writes for n, s in cage.physics.supplies.items()} == writes


def test_forced_past_the_check_the_coil_is_held_by_the_cage_limits(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The check bypassed, coil_x is a load channel: the 2.564 A set-point of the ramp (beyond
    the cage's 2.5 A for x) is refused at the coil's own write path, the run ends `error` naming
    coil_x, the value and the limit, and the coil never carries more than 2.5 A (watched in the
    simulator's physics every 2 ms): the field it makes stays within 120 uT."""
    monkeypatch.setattr(runner_module, "refuse_what_check_refuses", lambda *a: None)
    # and without the field guard, which would end it first (the reference reads 124.9 uT with
    # the lab field): the coil's own limits are the line under test
    monkeypatch.setattr(runner_module, "guard_the_field", lambda *a: None)
    proc = tmp_path / "p.yaml"
    proc.write_text(COIL_AS_LOAD)
    coil = cage.physics.supplies["coil_x"]
    peak = [0.0]

    def watch(t: float) -> None:
        peak[0] = max(peak[0], abs(coil.output_current(t)))

    outcome = run_watched(cage, rig_toml, proc, tmp_path / "runs", watch)
    assert outcome.status == "error", outcome.reason
    assert outcome.reason.startswith("coil_x: a set-point of 2.5641 A is beyond its 2.5 A limit"
                                     " (the cage's max_current_a for axis x)"), outcome.reason  # fmt: skip
    assert 2.3 < peak[0] <= 2.5, peak  # the ramp reached 2.44 A, and no further
    assert not any(s.output for s in cage.physics.supplies.values())
    # the reference saw the field the coil made: within the cage's 120 uT (the attack: 140 uT)
    from rig.store import RunReader

    reader = RunReader(outcome.folder)
    try:
        ref = np.array(reader.samples("reference"))
    finally:
        reader.close()
    # the lab field the coil adds to (on a busy machine the run may have no reference sample
    # before the step began to take it from)
    ambient = np.array(cage.physics.cfg.ambient.field_ut)
    made = np.linalg.norm(ref[:, 1:] - ambient, axis=1)
    assert 90.0 < made.max() < 120.0, made.max()


def test_a_load_channel_keeps_its_configured_max_current(
    cage: SimulatedCage, rig_toml: Path
) -> None:
    """``max_current_a`` of a load channel: a set-point beyond it never reaches the device."""
    rig_toml.write_text(rig_toml.read_text().replace("[devices.load_bus]\n",
                                                     "[devices.load_bus]\nmax_current_a = 1.5\n"))  # fmt: skip
    cfg = load_rig_config(rig_toml)
    supply = cage.physics.supplies["load_bus"]
    load = open_load(cfg.devices["load_bus"], cage.i2c_bus, cfg)
    try:
        load.set_current(1.5)
        with pytest.raises(OutputLimitError, match=r"load_bus: a set-point of 1\.6 A is beyond"
                                                   r" its 1\.5 A limit \(max_current_a of"):  # fmt: skip
            load.set_current(1.6)
        assert supply.i_set == pytest.approx(1.5)
    finally:
        load.safe()
        load.close()


def test_the_field_limit_current_is_the_most_any_legal_field_needs(rig_toml: Path) -> None:
    cfg = load_rig_config(rig_toml)
    model = cage_model(cfg)
    assert model is not None and cfg.cage is not None
    model = type(model)(model.k_ut_per_a, np.array([19.6, 1.2, -44.8]))  # with an ambient field
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(20000, 3))
    fields = 120.0 * directions / np.linalg.norm(directions, axis=1)[:, None]
    needed = np.abs(np.array([model.currents_a(f) for f in fields])).max(axis=0)
    for axis in range(3):
        bound = field_limit_current_a(model, 120.0, axis)
        assert needed[axis] <= bound + 1e-9 and needed[axis] > bound - 0.01
    # a coil's limit is the tightest of its range, the cage's current and the field limit
    limits = output_limits(cfg, cfg.devices["coil_y"], type("D", (), {"max_current_a": 6.0,
                                                                      "max_voltage_v": 60.0})())  # fmt: skip
    assert limits.max_current_a == 2.5 and limits.max_voltage_v == 12.0
