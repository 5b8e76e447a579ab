"""`rig cage characterize`, then `rig cage set-field --trim`, as a technician types them, on the
simulated cage in simulated time (ADR 0038): the command's whole path (its arguments, the file it
writes, what it prints, the safe state after) on a clock no busy computer can disturb. The same
commands against a `rig sim` process on the wall clock: tests/cage/test_cage_command.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rig.cli import main
from sim.config import load_config
from sim.physics import CagePhysics
from tests.simcage import sim_cage

pytestmark = pytest.mark.simcage


def test_characterize_then_trimmed_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with sim_cage(tmp_path) as (cage, rig_toml):
        code = main(["cage", "characterize", "--rig-config", str(rig_toml), "--repeats", "1",
                     "--samples", "5"])  # fmt: skip
        out = capsys.readouterr()
        assert code == 0, out.err
        assert "residual rms" in out.out and "wrote" in out.out
        cal = json.loads((rig_toml.parent / "cage-calibration.json").read_text())
        assert cal["schema"] == "rig.cage-calibration/1"
        # the truth of k_xx: the coil's 40.20 uT/A where the reference sits (40.1993) times its
        # supply's 150 ppm gain error and its gain's drift (sim/default_cage.toml, sim.physics);
        # the characterization's sigma is the promise it is judged by
        k_xx, k_xx_sigma = cal["k_ut_per_a"][0][0], cal["k_sigma_ut_per_a"][0][0]
        physics = CagePhysics(load_config(), start_s=0.0)
        truth = physics.coil_matrix_at["reference"][0, 0] * physics.coil_gains(60.0)[0]
        why = f"{out.out}\n{cal}"
        assert 0 < k_xx_sigma < 0.005 and abs(k_xx - truth) < 4 * k_xx_sigma, why
        code = main(["cage", "set-field", "10", "-5", "5", "--trim", "--hold", "0.3",
                     "--rig-config", str(rig_toml)])  # fmt: skip
        out = capsys.readouterr()
        assert code == 0, out.err
        assert "settled" in out.out and "outputs ramped down and off" in out.out
        on = [name for name, s in cage.physics.supplies.items() if s.output]
        assert not on, f"outputs left on: {on}"
