"""The shipped cage-metrology procedure on the simulated cage with its imperfections on (Biot-Savart
coils, city lab field, supply gain drift): the operator, played here, turns the simulated
reference on its fixture when asked, each turn off by tens of arcseconds; the coil constants and
axis angles come out within their sigmas of the simulator's truth where the reference sits."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from rig.cage.coil_axes import DEFAULT_POSITIONS, rotation
from rig.procedure_files import PROCEDURES_DIR
from sim.cage import SimulatedCage
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage

PROCEDURE = PROCEDURES_DIR / "cage-metrology.yaml"
ARCSEC = math.radians(1 / 3600)


class FixtureOperator:
    """Turns the reference to the position a prompt names, off by ``error_arcsec`` 1-sigma per
    axis (a fixture's real turns); confirms every other prompt."""

    def __init__(self, seed: int, error_arcsec: float = 30.0) -> None:
        self.rng = np.random.default_rng(seed)
        self.error_arcsec = error_arcsec
        self.turns: list[np.ndarray] = []

    def __call__(self, cage: SimulatedCage, question: str) -> bool:
        found = re.match(r"Fixture position (\d) of 4", question)
        if found:
            index = int(found[1]) - 1
            nominal = DEFAULT_POSITIONS[index][1]
            error = (
                self.error_arcsec * ARCSEC * self.rng.standard_normal(3) if index else np.zeros(3)
            )
            turn = nominal @ rotation(error)
            cage.physics.magnetometers["reference"].set_turn(turn)
            self.turns.append(turn)
        return True


def skews_arcsec(k: np.ndarray) -> np.ndarray:
    unit = k / np.linalg.norm(k, axis=0)
    return np.array([(math.pi / 2 - math.acos(unit[:, i] @ unit[:, j])) / ARCSEC
                     for i, j in ((0, 1), (0, 2), (1, 2))])  # fmt: skip


def test_the_metrology_procedure_recovers_the_simulated_coils(tmp_path: Path) -> None:
    operator = FixtureOperator(seed=11)
    truth: dict[str, np.ndarray] = {}

    def playing(cage: SimulatedCage, question: str) -> bool:
        physics = cage.physics
        truth["k"] = physics.coil_matrix_at["reference"] * physics.coil_gains()
        return operator(cage, question)

    outcome = run_on_sim(tmp_path, PROCEDURE.read_text(), operator=playing)
    assert outcome.exit_code == 0, outcome
    assert len(operator.turns) == 4
    result = outcome.results["coil axes"]
    k_true = truth["k"]
    skews = np.array([result["skew_arcsec"][p] for p in ("xy", "xz", "yz")])
    sigma = np.array([result["skew_sigma_arcsec"][p] for p in ("xy", "xz", "yz")])
    assert np.all(np.abs(skews - skews_arcsec(k_true)) < 4 * sigma), (
        skews,
        skews_arcsec(k_true),
        sigma,
    )
    consts = np.array([result["constants_ut_per_a"][a] for a in "xyz"])
    rel = 1e-6 * np.array([result["constants_sigma_ppm"][a] for a in "xyz"])
    true_consts = np.linalg.norm(k_true, axis=0)
    assert np.all(np.abs(consts / true_consts - 1) < 4 * rel), (consts, true_consts, rel)
    assert sigma.max() < 30 and rel.max() < 2e-4
