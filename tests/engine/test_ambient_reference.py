"""The cage's outside reference (``[cage] ambient``) is recorded in every run, whatever the
procedure names; what it reads is the lab field where it sits, which moves with the lab field at
the centre (minus the coils' far field, which it also sees)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rig.config import load_rig_config
from rig.store.run_store import RunReader
from tests.simcage import sim_cage
from tests.simrun import TINY_PROCEDURE, run_on_sim


def test_the_sim_rig_names_its_outside_reference(tmp_path: Path) -> None:
    with sim_cage(tmp_path) as (_, rig_toml):
        cfg = load_rig_config(rig_toml)
    assert cfg.cage is not None and (cfg.cage.reference, cfg.cage.ambient) == (
        "reference",
        "outside",
    )


def test_every_run_records_the_outside_reference(tmp_path: Path) -> None:
    outcome = run_on_sim(tmp_path, TINY_PROCEDURE)  # names only dut and reference
    assert outcome.exit_code == 0, outcome
    reader = RunReader(outcome.folder)
    assert {"dut", "reference", "outside"} <= set(reader.devices())
    rows = np.array(reader.samples("outside"))
    # about 10 per second over the run; the lab field there, not the cage's null
    assert len(rows) >= 5 and 30.0 < float(np.linalg.norm(rows[:, 1:].mean(axis=0))) < 70.0
