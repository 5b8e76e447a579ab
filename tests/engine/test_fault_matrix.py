"""The fault matrix in CI: the diagonal of faults x step kinds (every fault once, every step kind
that drives outputs at least once), a second run on a busy rig and SIGKILL of a cage command. Each
ends as its row says (retry, resync or abort to the safe state within its bounds), nothing
received is lost, and the reason names the culprit. bench/fault_matrix.py runs every cell and
writes docs/reliability.md."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.faultlab import EXTRA, FAULTS, STEP_KINDS, Fault, cells, run_extra, run_fault

DIAGONAL = cells(full=False)


def test_the_diagonal_covers_every_fault_and_step_kind() -> None:
    assert {f.key for f, _ in DIAGONAL} == {f.key for f in FAULTS}
    assert {k for _, k in DIAGONAL} == set(STEP_KINDS)


@pytest.mark.parametrize(("fault", "kind"), DIAGONAL, ids=[f"{f.key}-{k}" for f, k in DIAGONAL])
def test_fault_ends_as_expected(fault: Fault, kind: str, tmp_path: Path) -> None:
    measured = run_fault(fault, tmp_path, kind)
    assert measured.ok, measured.problems
    print(f"{fault.key} in {kind}: {measured.status}, detected {measured.detected_ms} ms,"
          f" safe {measured.safe_after_detection_ms} ms after")  # fmt: skip


@pytest.mark.parametrize("fault", EXTRA, ids=[f.key for f in EXTRA])
def test_interlock_and_cage_command_cells(fault: Fault, tmp_path: Path) -> None:
    measured = run_extra(fault, tmp_path)
    assert measured.ok, measured.problems
