"""A slow Modbus link (a 9600-baud RS-485 bus, a busy gateway) must cost time, never correctness:
a read-back asked before a load change and answered after it is not taken as the new current."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rig.analysis import calibration_data
from rig.steps import field_kinds
from rig.store import RunReader
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage

PROCEDURE = """
procedure: load steps over a slow link
magnetometers: {dut: dut, reference: reference}
loads: [load_panel]
steps:
  - set_field: {field_ut: [20, 10, -30], hold_s: 0.5}
  - hold: {hold_s: 6}
    name: steps
    loads:
      load_panel: {steps: {levels_a: [0.0, 2.0, 0.5, 2.5], dwell_s: 1.5}}
"""


def test_load_telemetry_of_every_settled_sample_is_the_current_then_set(tmp_path: Path) -> None:
    """0.1 s per reply on the load: the monitor's read-backs overlap every change. Each settled
    sample's telemetry must be the level the load was set to (before: the old level for up to
    0.3 s after a change, 1.1 uT errors in the fit)."""
    outcome = run_on_sim(tmp_path, PROCEDURE, reply_delay_s={"load_panel": 0.1})
    assert outcome.status == "complete", outcome.reason
    reader = RunReader(outcome.folder)
    try:
        samples, t, *_ = calibration_data(reader, "dut", "reference", ["load_panel"], ["steps"], 0.25,
                                      None, field_kinds())  # fmt: skip
        sets = [(tt, p["current_a"]) for tt, _, k, p in reader.commands() if k == "load"]
    finally:
        reader.close()
    assert samples.telemetry is not None and samples.n > 40
    set_t = np.array([s[0] for s in sets])
    level = np.array([s[1] for s in sets])[np.searchsorted(set_t, t, side="right") - 1]
    assert len(set(level)) == 4  # every level has settled samples
    wrong = np.abs(samples.telemetry[:, 0] - level) > 0.01
    assert not wrong.any(), list(
        zip(t[wrong], samples.telemetry[wrong, 0], level[wrong], strict=True)
    )
