"""`echo y | rig run` on a procedure that asks the operator: refused before anything starts (no
run folder, nothing for the lab index, no output switched on), with the ways to answer (issue 33)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

PROCEDURE = """
procedure: asks first
magnetometers: {dut: dut}
steps:
  - null_field: {hold_s: 1}
  - prompt: "Rotate the DUT by 90 degrees"
"""


def test_piped_answers_are_refused_before_the_run_starts(tmp_path: Path) -> None:
    (tmp_path / "proc.yaml").write_text(PROCEDURE)
    (tmp_path / "rig.toml").write_text(
        '[devices.dut]\nkind = "hmr2300"\nprotocol = "serial"\npath = "/dev/null"\n'
    )
    runs = tmp_path / "runs"
    proc = subprocess.run(
        [sys.executable, "-m", "rig.cli", "run", str(tmp_path / "proc.yaml"), "--rig",
         str(tmp_path / "rig.toml"), "--runs-dir", str(runs)],
        input="y\n", capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert "proc.yaml:6: step 2 (prompt) asks the operator a question" in line, line
    assert "--serve" in line and "--yes" in line
    assert not runs.exists() or not any(runs.iterdir())
