"""``supply_stability`` on the simulated cage: a coil supply whose gain drifts (hidden from its
read-back) under the simulated city lab field (slow drifts of tens of nT, traffic, 1/f noise);
the drift of the inner reference less the outside one is the coils' drift."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sim.cage import SimulatedCage
from sim.config import load_config
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage

DRIFT_PPM_PER_H = 40000.0  # a supply far out of spec, so that 40 s show it

PROCEDURE = """
procedure: Drift
magnetometers: {dut: reference, reference: reference}
steps:
  - supply_stability: {field_ut: [0, 0, 40], hold_s: 40}
    name: drift
  - prompt: "Note the coil currents"
"""


def test_the_coils_drift_is_found_under_the_lab_fields_changes(tmp_path: Path) -> None:
    cfg = load_config()
    cfg = replace(cfg, supplies=tuple(replace(s, gain_drift_ppm_per_h=DRIFT_PPM_PER_H)
                                      if s.name == "coil_z" else s for s in cfg.supplies))  # fmt: skip
    seen: dict[str, np.ndarray] = {}

    def operator(cage: SimulatedCage, question: str) -> bool:
        physics = cage.physics
        currents = physics.coil_currents()
        seen["rate"] = physics.coil_matrix_at["reference"] @ (currents * np.array(
            [s.gain_drift_ppm_per_h for s in sorted(
                (s for s in physics.cfg.supplies if s.axis is not None), key=lambda s: s.axis)]))  # fmt: skip
        return True

    outcome = run_on_sim(tmp_path, PROCEDURE, sim_config=cfg, operator=operator)
    assert outcome.exit_code == 0, outcome
    result = outcome.results["drift"]
    truth_nt_per_h = 1e-3 * seen["rate"]  # uT/A * A * ppm/h -> nT/h
    drift = np.array([result["drift_nt_per_h"][a] for a in "xyz"])
    sigma = np.array([result["drift_sigma_nt_per_h"][a] for a in "xyz"])
    assert truth_nt_per_h[2] > 10 * sigma[2], (truth_nt_per_h, sigma)
    assert np.all(np.abs(drift - truth_nt_per_h) < 4 * sigma), (drift, truth_nt_per_h, sigma)
