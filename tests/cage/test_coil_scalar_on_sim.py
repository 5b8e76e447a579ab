"""The shipped scalar cage-metrology procedure on the simulated cage with its imperfections on
(Biot-Savart coils, city lab field, supply gain drift) and its cesium sensor behind a CM-201
counter (dead zones, heading error, absolute offset): no operator, no certificate; the coil
constants and axis angles come out within their sigmas of the simulator's truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rig.cage.model import CageModel
from rig.procedure_files import PROCEDURES_DIR
from sim.cage import SimulatedCage
from tests.cage.test_coil_axes_on_sim import skews_arcsec
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage

PROCEDURE = PROCEDURES_DIR / "cage-metrology-scalar.yaml"


def test_the_scalar_procedure_recovers_the_simulated_coils(tmp_path: Path) -> None:
    truth: dict[str, np.ndarray] = {}

    def operator(cage: SimulatedCage, question: str) -> bool:
        truth["k"] = cage.physics.coil_matrix_at["cesium"] * cage.physics.coil_gains()
        return True

    outcome = run_on_sim(tmp_path, PROCEDURE.read_text(), operator=operator)
    assert outcome.exit_code == 0, outcome
    result = outcome.results["scalar coils"]
    k_true = truth["k"]
    skews = np.array([result["skew_arcsec"][p] for p in ("xy", "xz", "yz")])
    sigma = np.array([result["skew_sigma_arcsec"][p] for p in ("xy", "xz", "yz")])
    assert np.all(np.abs(skews - skews_arcsec(k_true)) < 4 * sigma), (skews, sigma)
    consts = np.array([result["constants_ut_per_a"][a] for a in "xyz"])
    rel = 1e-6 * np.array([result["constants_sigma_ppm"][a] for a in "xyz"])
    true_consts = np.linalg.norm(k_true, axis=0)
    assert np.all(np.abs(consts / true_consts - 1) < 4 * rel), (consts, true_consts, rel)
    assert sigma.max() < 30 and rel.max() < 2e-4
    assert result["points"] >= 20 and len(result["readings"]) == result["points"]
    assert abs(result["sensor_offset_nt"] - 1.4) < 4 * result["sensor_offset_sigma_nt"] + 0.5
    kept = CageModel.load(tmp_path / "cage-calibration.json").metrology()["coil_scalar"]
    assert kept["result"]["constants_ut_per_a"] == result["constants_ut_per_a"]
