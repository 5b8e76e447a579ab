"""The fault matrix in CI: every fault, injected into the simulated cage mid-run, ends as its row
says (retry, resync or abort to the safe state within its bound), nothing received is lost, and
the reason names the culprit. docs/reliability.md holds the measured figures."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.faultlab import FAULTS, Fault, run_fault


@pytest.mark.parametrize("fault", FAULTS, ids=[f.key for f in FAULTS])
def test_fault_ends_as_expected(fault: Fault, tmp_path: Path) -> None:
    measured = run_fault(fault, tmp_path)
    assert measured.ok, measured.problems
    print(f"{fault.key}: {measured.status}, safe in {measured.time_to_safe_ms} ms")
