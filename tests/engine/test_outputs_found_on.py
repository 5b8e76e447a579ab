"""Outputs found on at the start of a run are switched off before anything else, and the end of
the run states what was read back (issue 51: after SIGKILL of both the rig and its guardian the
next `rig run smoke` ran with the heater at 2 A throughout and said every output was off).

The heater at 2 A and coil_x at 1 A are driven through the drivers and their links closed, as the
two dead processes leave them; then rig/shipped_procedures/smoke.yaml is run on the simulated cage in
simulated time, with the heater's true output sampled every 2 ms from the simulator's physics."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import timebase
from rig.config import load_rig_config
from rig.devices import open_device
from rig.engine.runner import Runner
from rig.engine.session import RigSession
from rig.errors import RigError
from rig.procedure.language import parse_procedure
from rig.procedure_files import PROCEDURES_DIR
from rig.store import RunReader
from sim.cage import SimulatedCage
from tests.simcage import sim_cage

SMOKE = PROCEDURES_DIR / "smoke.yaml"

pytestmark = [pytest.mark.realtime, pytest.mark.usefixtures("own_lock_dir")]


def drive(rig_toml: Path) -> None:
    """The heater at 2 A and coil_x at 1 A through their drivers, links closed, outputs on."""
    cfg = load_rig_config(rig_toml)
    for name, amps in (("heater", 2.0), ("coil_x", 1.0)):
        supply = open_device(cfg.devices[name])
        try:
            supply.set_voltage(12.0)
            supply.set_current(amps)
            supply.set_output(True)
        finally:
            supply.close()


def test_outputs_found_on_are_switched_off_before_the_first_step(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """In simulated time: the run and the cage on one clock, the heater's true output sampled
    every 2 ms of it (in real time, beside two CPU hogs and three other test workers, the cage
    sharing this process starved: "reference: no data for 1.8 s", a fault no idle rig shows)."""
    with sim_cage(tmp_path) as (cage, rig_toml):
        heater = cage.physics.supplies["heater"]
        drive(rig_toml)
        deadline = timebase.monotonic() + 2.0
        while heater.output_current() < 1.9 and timebase.monotonic() < deadline:
            timebase.sleep(0.01)
        assert heater.output and heater.output_current() > 1.9
        samples: list[tuple[float, bool, float]] = []  # (monotonic s, output on, true current A)
        stop = timebase.Event()

        def watch() -> None:
            while not stop.wait(0.002):
                samples.append((timebase.monotonic(), heater.output, heater.output_current()))

        watcher = timebase.Thread(watch, name="heater-watch", daemon=True)
        watcher.start()
        runs = tmp_path / "runs"
        try:
            outcome = Runner(parse_procedure(SMOKE), load_rig_config(rig_toml), runs,
                             i2c_bus=cage.i2c_bus, confirm=lambda q: True, live=False).run()  # fmt: skip
        finally:
            stop.set()
            watcher.join(1.0)
        off_at = heater.off_since_s
    err = capsys.readouterr().err
    assert outcome.status == "complete", (outcome.reason, err[-2000:])
    said = [ln for ln in err.splitlines() if "was found on at the start" in ln]
    assert len(said) == 2, err  # the heater and coil_x, one line each
    heater_line = next(ln for ln in said if "heater was found on" in ln)
    assert re.search(r"heater was found on at the start \(output enabled, 2\.\d{3} A read"
                     r" back\); switched off before anything else, read back: heater: off"
                     r" \(0\.0[01]\d A read back\)", heater_line), heater_line  # fmt: skip
    end = outcome.outputs
    assert end.startswith("outputs: read back off: coil_x 0.0"), end
    assert "heater 0.0" in end and end.endswith("polarity normal"), end
    folder = next(p for p in runs.iterdir() if (p / "run.sqlite").exists())
    reader = RunReader(folder)
    try:
        events = reader.events()
        steps = reader.steps()
        first_command = min(t for t, *_ in reader.commands())
    finally:
        reader.close()
    found = [(t, lvl) for t, lvl, m in events if "heater was found on at the start" in m]
    assert len(found) == 1 and found[0][1] == "warning", events
    t_first_step = min(s[3] for s in steps)
    assert found[0][0] < t_first_step and found[0][0] < first_command
    assert end in [m for _, lvl, m in events if lvl == "info"]  # recorded in the run too
    during = [(on, amps) for t, on, amps in samples if t >= t_first_step]
    assert len(during) > 3000, len(during)  # the run's ~15 s, every 2 ms of the run's clock
    assert not any(on for on, _ in during)
    peak = max(amps for _, amps in during)
    assert peak < 0.01, peak
    assert off_at is not None and off_at < t_first_step
    print(
        f"heater found on at 2 A: off {t_first_step - off_at:.2f} s before the first step;"
        f" {len(during)} samples during the run, peak {1000 * peak:.1f} mA, never on"
    )


def test_an_output_that_cannot_be_read_at_the_start_refuses_the_command(
    cage: SimulatedCage, rig_toml: Path
) -> None:
    """load_panel does not answer and the heater is on: the session switches the heater off and
    refuses in one line naming load_panel and `rig safe`, before anything is opened."""
    drive(rig_toml)
    cage.faults["load_panel"].silent = True
    try:
        with (
            pytest.raises(RigError) as refused,
            RigSession(load_rig_config(rig_toml), command="test", guardian=False),
        ):
            raise AssertionError("the session started")
    finally:
        cage.faults["load_panel"].silent = False
    message = str(refused.value)
    assert "\n" not in message
    assert re.search(r"load_panel: could not confirm off: reading it at 127\.0\.0\.1:\d+ id 1"
                     r" failed", message), message  # fmt: skip
    assert message.endswith(f"then run 'rig safe --rig {rig_toml}' and start again"), message
    supplies = cage.physics.supplies
    assert not [n for n, s in supplies.items() if s.output and n != "load_panel"]
