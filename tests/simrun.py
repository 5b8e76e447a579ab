"""Run a procedure text on an in-process simulated cage (for tests of steps and the engine)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import timebase
from rig.config import load_rig_config
from rig.engine.runner import Runner, RunOutcome
from rig.procedure.language import parse_procedure
from sim.cage import SimulatedCage
from sim.config import SimConfig
from tests.simcage import sim_cage


def run_on_sim(
    folder: Path, procedure: str, reply_delay_s: dict[str, float] | None = None,
    sim_config: SimConfig | None = None,
    operator: Callable[[SimulatedCage, str], bool] | None = None, *, simulated: bool = True,
    busy: timebase.BusyHost | None = None,
) -> RunOutcome:  # fmt: skip
    """Write ``procedure`` (YAML text) to ``folder``, run it on a fresh simulated cage with every
    prompt confirmed and no live view, and return the outcome. ``reply_delay_s`` slows devices'
    replies (device name -> seconds), as a slow link would; ``sim_config`` replaces the default
    simulated cage; ``operator(cage, question)`` answers the prompts instead (and may act on the
    simulated cage, as an operator turning a fixture does). ``simulated``: on a fresh simulated
    clock (ADR 0038), else in real time; ``busy``: that clock's host threads wake late, as on a
    busy computer (timebase.busy_host)."""
    (folder / "procedure.yaml").write_text(procedure)
    with sim_cage(folder, sim_config, simulated=simulated, busy=busy) as (cage, rig_toml):
        for name, delay in (reply_delay_s or {}).items():
            cage.faults[name].reply_delay_s = delay

        def confirm(question: str) -> bool:
            return True if operator is None else operator(cage, question)

        return Runner(parse_procedure(folder / "procedure.yaml"), load_rig_config(rig_toml),
                      folder / "runs", i2c_bus=cage.i2c_bus, confirm=confirm, live=False).run()  # fmt: skip


def run_watched(cage: SimulatedCage, rig_toml: Path, procedure: Path, runs: Path,
                watch: Callable[[float], None], period_s: float = 0.002) -> RunOutcome:  # fmt: skip
    """Run ``procedure`` (a file) on the running ``cage`` in this process, every prompt confirmed,
    while ``watch(t)`` (t: monotonic s) is called every ``period_s`` from a thread of its own:
    the simulator's truth read as the run goes (coil currents, field, temperature)."""
    stop = timebase.Event()

    def watching() -> None:
        while not stop.wait(period_s):
            watch(timebase.monotonic())

    watcher = timebase.Thread(watching, name="truth-watch", daemon=True)
    watcher.start()
    try:
        return Runner(parse_procedure(procedure), load_rig_config(rig_toml), runs,
                      i2c_bus=cage.i2c_bus, confirm=lambda s: True, live=False).run()  # fmt: skip
    finally:
        stop.set()
        watcher.join(1.0)


TINY_PROCEDURE = """
procedure: Tiny
magnetometers: {dut: dut, reference: reference}
parameters:
  dut_serial: {default: SN-0042}
  lot: {default: "7"}
steps:
  - null_field: {hold_s: 1}
    name: noise floor
  - check:
      criteria:
        - {result: noise floor, value: dut_noise_nt, max: 200, name: DUT noise at null field}
"""
"""A null field and a check on it, a few seconds: a closed run with a verdict (serial SN-0042,
lot 7)."""
