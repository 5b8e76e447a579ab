"""The cage's field limit held against the field made, not only the field modelled (issue 51).

On an uncharacterized cage (nominal coil constants, the lab field taken as 0), a 95 uT field on z
that `rig check` approved made the reference read 142.1 uT against a 120 uT limit, and the run
passed. Now the dry run counts the lab field until a characterization measures it (the field
asked plus up to 66 uT must stay within the limit), so `rig check` and `rig run` refuse it; and
forced past that refusal, the reference's reading beyond the limit ends the run with every output
off."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import rig.engine.runner as runner_module
from rig.cli import main
from sim.cage import SimulatedCage
from tests.simrun import run_watched
from tests.test_check_cage_model import CHARACTERIZE, write

Z_95 = "  - set_field: {field_ut: [0, 0, -95], hold_s: 2}\n"  # the lab field is -44.8 uT on z
Z_50 = "  - set_field: {field_ut: [0, 0, 50], hold_s: 2}\n"

pytestmark = [pytest.mark.realtime, pytest.mark.usefixtures("own_lock_dir")]


def check(tmp_path: Path, steps: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    proc, cfg = write(tmp_path, steps)
    code = main(["check", str(proc), "--rig", str(cfg)])
    return code, [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("LIMIT:")]


def test_the_unmeasured_lab_field_counts_against_the_field_limit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, limits = check(tmp_path, Z_95, capsys)
    assert code == 1 and len(limits) == 1, limits
    assert "|B| = 95.0 uT with the lab field not yet measured (up to 66 uT" in limits[0]
    assert "may reach 161.0 uT, beyond the 120 uT limit: characterize the cage first" in limits[0]
    # 50 + 66 stays within 120; after a characterization the lab field is measured and cancelled
    assert check(tmp_path, Z_50, capsys) == (0, [])
    assert check(tmp_path, CHARACTERIZE + Z_95, capsys) == (0, [])


def test_forced_past_the_check_the_measured_field_takes_the_outputs_safe(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The refusal bypassed, the run asks -95 uT on z of a cage whose lab field it does not know:
    the reference's reading beyond 120 uT (plus its margin) ends the run `error` naming it, every
    supply is off, and the true field is brought down at once rather than held at 142 uT."""
    monkeypatch.setattr(runner_module, "refuse_what_check_refuses", lambda *a: None)
    proc = tmp_path / "z95.yaml"
    proc.write_text("procedure: Z95\nmagnetometers: {dut: dut, reference: reference}\nsteps:\n"
                    + Z_95.replace("hold_s: 2", "hold_s: 6"))  # fmt: skip
    physics = cage.physics
    above: list[float] = []  # true |B| at the DUT beyond 120 uT, every 2 ms

    def watch(t: float) -> None:
        b = float(np.linalg.norm(physics.field_ut(t, noise=False)))
        if b > 120.0:
            above.append(b)

    outcome = run_watched(cage, rig_toml, proc, tmp_path / "runs", watch)
    assert outcome.status == "error", outcome.reason
    assert outcome.reason.startswith("reference reads |B| = 1"), outcome.reason
    assert "beyond the cage's 120 uT limit (max_field_ut)" in outcome.reason
    assert not any(s.output for s in physics.supplies.values())
    # beyond the limit only while the guard saw it and the ramp down began: well under the 6 s
    # the step would have held it (0.002 s per watched point)
    assert len(above) * 0.002 < 2.0, len(above)
