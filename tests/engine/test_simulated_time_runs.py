"""Whole runs of shipped procedures on the simulated cage in simulated time (ADR 0038): the same
procedure, rig file and seed give the same measurements to the bit in another process and beside
CPU hogs, and the report says the run was simulated."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from rig.store.run_store import RunReader
from rig.store.seal import measurement_digest
from tests.drivers.wire_devices import cpu_hogs

pytestmark = pytest.mark.simcage


def demo(runs: Path, procedure: str = "smoke") -> Path:
    """``rig demo --simulated-time`` in a process of its own; the run's folder."""
    done = subprocess.run([sys.executable, "-m", "rig.cli", "-q", "demo", "--simulated-time",
                           "--procedure", procedure, "--runs-dir", str(runs)],
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr
    (folder,) = [p for p in runs.iterdir() if (p / "run.sqlite").exists()]
    return folder


def test_the_same_run_twice_alone_and_beside_cpu_hogs_measures_the_same(tmp_path: Path) -> None:
    alone = demo(tmp_path / "alone")
    with cpu_hogs(2):
        busy = demo(tmp_path / "busy")
    assert measurement_digest(alone / "run.sqlite") == measurement_digest(busy / "run.sqlite")
    reader = RunReader(alone)
    meta = reader.meta()
    samples = reader.count("samples")
    reader.close()
    assert meta["clock"] == "simulated" and meta["status"] == "complete" and samples > 200
    text = (alone / "report.txt").read_text(encoding="utf-8")
    assert "SIMULATED: a dry run on the simulated cage in simulated time" in text
