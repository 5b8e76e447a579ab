"""Both kinds of commercial relay board switching the cage's polarity through a procedure on the
simulated cage, in simulated time: a coil board (regmaps/waveshare-relay.toml: function 05,
read by 01) and a command-register board (regmaps/r421a08-relay.toml: function 06 0x0100 on,
0x0200 off, read by 03), each on a Modbus RTU line at 9600 Bd as sold. Nulling the lab field
(19.6, 1.2, -44.8 uT) drives x and y backwards, +30 uT on x forwards, -30 uT backwards again,
and y alike: the x and y relays switch back and forth, never while their coil carries current
(no hot switch), the field the reference measures follows the sign asked (+30 and -30 uT steps
60 uT apart), and the run's safe path leaves every relay off."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rig.config import load_rig_config
from rig.engine.runner import Runner
from rig.procedure.language import parse_procedure
from rig.store import RunReader
from sim.config import EndpointConfig, load_config
from tests.simcage import sim_cage

pytestmark = pytest.mark.simcage

PROCEDURE = """
procedure: Polarity through the relay board
magnetometers: {dut: dut, reference: reference}
steps:
  - null_field: {hold_s: 1, trim: yes}
  - set_field: {field_ut: [30, 0, 0], hold_s: 1}
    name: plus x
  - set_field: {field_ut: [-30, 0, 0], hold_s: 1}
    name: minus x
  - set_field: {field_ut: [0, 30, 0], hold_s: 1}
    name: plus y
  - set_field: {field_ut: [0, -30, 0], hold_s: 1}
    name: minus y
"""


def step_mean_ut(reader: RunReader, name: str) -> np.ndarray:
    """The reference's mean reading (uT) over the last half second of step ``name``."""
    end = next(t1 for _, n, _, _, t1 in reader.steps() if n == name)
    assert end is not None, name
    rows = np.array([s[1:] for s in reader.samples("reference") if end - 0.5 <= s[0] <= end])
    assert len(rows) >= 5, name
    return np.asarray(rows.mean(axis=0))


@pytest.mark.parametrize("regmap", ["waveshare-relay", "r421a08-relay"])
def test_a_procedure_switches_polarity_through_each_kind_of_relay_board(
    tmp_path: Path, regmap: str
) -> None:
    cfg = load_config()
    assert cfg.relay is not None
    board = replace(cfg.relay, regmap=regmap, endpoint=EndpointConfig("modbus-rtu", 1, 9600))
    (tmp_path / "procedure.yaml").write_text(PROCEDURE)
    with sim_cage(tmp_path, replace(cfg, relay=board)) as (cage, rig_toml):
        assert cage.endpoints["polarity"]["regmap"].endswith(f"{regmap}.toml")
        outcome = Runner(parse_procedure(tmp_path / "procedure.yaml"), load_rig_config(rig_toml),
                         tmp_path / "runs", i2c_bus=cage.i2c_bus, confirm=lambda q: True,
                         live=False).run()  # fmt: skip
        relays = cage.physics.relays
        switches, hot, signs = list(relays.switches), relays.hot_switches, list(relays.sign)
    assert outcome.status == "complete", outcome.reason
    assert switches[0] >= 3 and switches[1] >= 3  # x: null (back), +x, -x (back), off; y alike
    assert hot == 0 and signs == [1, 1, 1]  # never under current; every relay off at the end
    reader = RunReader(outcome.folder)
    try:
        plus_x, minus_x = step_mean_ut(reader, "plus x"), step_mean_ut(reader, "minus x")
        plus_y, minus_y = step_mean_ut(reader, "plus y"), step_mean_ut(reader, "minus y")
    finally:
        reader.close()
    assert plus_x[0] - minus_x[0] == pytest.approx(60.0, abs=3.0)
    assert plus_y[1] - minus_y[1] == pytest.approx(60.0, abs=3.0)
