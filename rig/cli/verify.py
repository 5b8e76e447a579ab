"""``rig verify RUN``: is the run folder as it was sealed when the run closed?"""

from __future__ import annotations

import argparse
from pathlib import Path

from rig.cli.common import Parser, Subparsers, resolve_run
from rig.errors import UserInputError


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    ver = sub.add_parser(
        "verify",
        parents=parents,
        help="check that a run folder is as it was sealed (data, configuration, reports)",
        description="Recompute the run's data SHA-256 and compare it with the seal written when"
        " the run closed, the sealed procedure and rig configuration copies, and the digest every"
        " report states. Exit 0 when intact, 1 when anything changed or the run is not sealed.",
    )
    ver.add_argument("run", metavar="RUN", help="run folder or run id")
    ver.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR",
                     help="where run ids are looked up (default: runs)")  # fmt: skip
    ver.set_defaults(func=_cmd_verify)


def _cmd_verify(args: argparse.Namespace) -> int:
    return verify(resolve_run(args.run, args.runs_dir), args.quiet)


def verify(folder: Path, quiet: bool) -> int:
    """Recompute the run's data digest and compare it with the seal, the sealed copies and every
    report. Prints INTACT or CHANGED and what was found; exit 0 intact, 1 otherwise."""
    from rig.store.seal import verify_run

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
