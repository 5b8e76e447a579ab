"""The acceptance record a run writes itself: final status and verdict in every report file, one
data digest however often the report is rebuilt, and `rig verify` that notices any change."""

from __future__ import annotations

import json
import re
import shutil
import sqlite3
import subprocess
from pathlib import Path

import pytest

from rig.cli import main
from rig.config import load_rig_config
from rig.engine.runner import Runner
from rig.procedure.language import parse_procedure
from rig.report.acceptance import build_report
from rig.store.seal import SEAL_FILE, data_digest, verify_run
from tests.simcage import sim_cage

pytestmark = pytest.mark.simcage

PROCEDURE = """procedure: Record test
parameters:
  dut_serial: {default: SN-REC}
magnetometers: {dut: dut, reference: reference}
steps:
  - null_field: {hold_s: 1}
    name: noise floor
  - sphere_sweep: {directions: 8, magnitude_ut: [25, 40], dwell_s: 1.2}
    name: sweep
  - calibrate: {model: vector, steps: [sweep]}
    name: vector calibration
  - report: {}
  - check:
      criteria:
        - {result: noise floor, value: dut_noise_nt, max: 500, name: DUT noise floor}
        - {result: vector calibration, value: residual_rms_nt, max: 500, name: vector residual}
"""


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One short run on the simulated cage whose procedure asks for the report *before* its
    check step (the report must still show the verdict)."""
    tmp = tmp_path_factory.mktemp("record")
    (tmp / "record.yaml").write_text(PROCEDURE)
    with sim_cage(tmp) as (cage, rig_toml):
        outcome = Runner(
            parse_procedure(tmp / "record.yaml"),
            load_rig_config(rig_toml),
            tmp / "runs",
            i2c_bus=cage.i2c_bus,
            confirm=lambda s: True,
            live=False,
            quiet=True,
        ).run()
    assert outcome.status == "complete", outcome.reason
    return outcome.folder


def _pdf_text(path: Path) -> str:
    return subprocess.run(
        ["pdftotext", "-layout", str(path), "-"], capture_output=True, text=True, check=True
    ).stdout


def test_the_report_the_run_wrote_shows_final_status_verdict_and_digest(
    recorded_run: Path,
) -> None:
    digest, _ = data_digest(recorded_run / "run.sqlite")
    seal = json.loads((recorded_run / SEAL_FILE).read_text())
    assert seal["data_sha256"] == digest and seal["status"] == "complete"
    txt = (recorded_run / "report.txt").read_text()
    html = (recorded_run / "report.html").read_text()
    pdf = _pdf_text(recorded_run / "report.pdf")
    for name, text in (("txt", txt), ("html", html), ("pdf", pdf)):
        assert "VERDICT: PASS" in text, name
        assert "RUNNING" not in text and "NOT A VALID" not in text, name
        assert digest in text, name
    assert re.search(r"Status: +complete \(all steps done\)", txt)
    assert "<th>Status</th><td>complete (all steps done)</td>" in html
    # criteria carry their units
    assert re.search(r"DUT noise floor +[0-9.]+ nT +max 500 nT +[0-9.]+ nT +PASS", txt)
    assert verify_run(recorded_run).intact, verify_run(recorded_run).problems


def test_rebuilding_the_report_keeps_the_digest_and_verify_notices_changes(
    recorded_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / recorded_run.name
    shutil.copytree(recorded_run, run)
    digest, _ = data_digest(run / "run.sqlite")
    for _ in range(2):
        build_report(run)
        assert data_digest(run / "run.sqlite")[0] == digest
        assert f"data sha256 {digest}" in (run / "report.txt").read_text()
    assert main(["verify", str(run)]) == 0
    assert "INTACT" in capsys.readouterr().out

    # one sample changed by a tenth of a nanotesla: the data no longer match the seal or reports
    con = sqlite3.connect(run / "run.sqlite")
    con.execute("UPDATE samples SET x = x + 0.0001 WHERE rowid = 10")
    con.commit()
    con.close()
    result = verify_run(run)
    assert not result.intact
    assert any("data changed since the run was sealed" in p for p in result.problems)
    assert any(p.startswith("report.txt states data sha256") for p in result.problems)
    assert main(["verify", str(run)]) == 1
    out = capsys.readouterr().out
    assert "CHANGED" in out and "data changed since the run was sealed" in out
    build_report(run)  # a rebuilt report says so on its face
    assert "DATA CHANGED SINCE THE RUN WAS SEALED" in (run / "report.txt").read_text()


def test_digest_ignores_file_layout_but_not_content(tmp_path: Path) -> None:
    from rig.store import new_run

    w = new_run(tmp_path, "SN-1", procedure="p")
    for i in range(200):
        w.add_sample(float(i), "dut", (float(i), 2.0, 3.0))
    assert w.close("complete", "done") == []
    folder = next(tmp_path.iterdir())
    digest = json.loads((folder / SEAL_FILE).read_text())["data_sha256"]
    con = sqlite3.connect(folder / "run.sqlite")
    con.execute("VACUUM")
    con.close()
    assert data_digest(folder / "run.sqlite")[0] == digest  # a vacuumed copy is the same data
    assert verify_run(folder).intact
    (folder / "procedure.yaml").write_text("changed")  # it did not exist at close: added
    result = verify_run(folder)
    assert not result.intact and list(result.changed) == ["files"], result.problems
    assert result.problems == ["procedure.yaml added (the rig did not write it)"]
