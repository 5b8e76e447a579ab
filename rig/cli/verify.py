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
        help="check that a run folder is as it was sealed (data, reports, every file)",
        description="Recompute the run's data SHA-256 and compare it with the seal written when"
        " the run closed, the sealed procedure and rig configuration copies, and the digest every"
        " report states, and every file of the folder against its manifest (edited, deleted or"
        " added files; tables added or dropped). The headline says apart the data, the reports"
        " and other files. Exit 0 when intact, 1 when anything changed or the run is not sealed,"
        " 2 when RUN is not a readable run folder (missing, damaged, a link).",
    )
    ver.add_argument("run", metavar="RUN", help="run folder or run id")
    ver.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR",
                     help="where run ids are looked up (default: runs)")  # fmt: skip
    ver.set_defaults(func=_cmd_verify)


def _cmd_verify(args: argparse.Namespace) -> int:
    return verify(resolve_run(args.run, args.runs_dir), args.quiet)


def verify(folder: Path, quiet: bool) -> int:
    """Recompute the run's data digest and compare it with the seal, the manifest (every file of
    the folder) and every report. Prints one headline, INTACT or CHANGED naming what changed (the
    data, the reports, other files: each said apart), then the details; exit 0 intact, 1 changed
    or not sealed, 2 not a readable run folder."""
    import sqlite3

    from rig.store.seal import AREAS, damaged, verify_run

    if not (folder / "run.sqlite").exists():
        raise UserInputError(
            f"{folder}: not a run folder (no run.sqlite); list runs with 'rig runs'"
        )
    try:
        result = verify_run(folder)
    except sqlite3.DatabaseError as exc:
        raise damaged(folder, exc) from None
    except OSError as exc:  # a file or sub-folder the account may not read
        raise UserInputError(
            f"{folder}: cannot read {exc.filename or 'the run folder'} ({exc.strerror}); verify"
            " as the run's owner"
        ) from None
    scope = "" if result.manifest else "; data and sealed copies only: the run has no manifest"
    if result.intact:
        if not quiet:
            print(f"{folder.name}: INTACT (data sha256 {result.data_sha256}{scope})")
            for line in result.findings:
                print(f"  ok       {line}")
        return 0
    if not result.sealed:
        print(f"{folder.name}: NOT SEALED (data sha256 now {result.data_sha256})")
    else:
        verdicts = ", ".join(
            f"{NAMES[a]} {'CHANGED' if a in result.changed else 'intact'}" for a in AREAS
        )
        print(f"{folder.name}: CHANGED ({verdicts}{scope})")
    for area in AREAS:
        for line in result.changed.get(area, []):
            print(f"  {area.upper():<8} {line}")
    if not quiet:
        for line in result.findings:
            print(f"  ok       {line}")
    return 1


NAMES = {"data": "data", "reports": "reports", "files": "other files"}
