"""``rig verify RUN``: is the run folder as it was sealed when the run closed?"""

from __future__ import annotations

from pathlib import Path

from rig.errors import UserInputError
from rig.store.seal import verify_run


def verify(folder: Path, quiet: bool) -> int:
    """Recompute the run's data digest and compare it with the seal, the sealed copies and every
    report. Prints INTACT or CHANGED and what was found; exit 0 intact, 1 otherwise."""
    if not (folder / "run.sqlite").exists():
        raise UserInputError(
            f"{folder}: not a run folder (no run.sqlite); list runs with 'rig runs'"
        )
    result = verify_run(folder)
    if result.intact:
        if not quiet:
            print(f"{folder.name}: INTACT (data sha256 {result.data_sha256})")
            for line in result.findings:
                print(f"  ok       {line}")
        return 0
    state = "CHANGED" if result.sealed else "NOT SEALED"
    print(f"{folder.name}: {state} (data sha256 now {result.data_sha256})")
    for line in result.problems:
        print(f"  PROBLEM  {line}")
    if not quiet:
        for line in result.findings:
            print(f"  ok       {line}")
    return 1
