"""``rig runs``: the recorded runs, newest first, with status and verdict."""

from __future__ import annotations

import argparse
from pathlib import Path

from rig.cli.common import Parser, Subparsers, add_runs_dir


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    runs = sub.add_parser("runs", parents=parents, help="list recorded runs")
    add_runs_dir(runs)
    runs.set_defaults(func=_cmd_runs)


def _cmd_runs(args: argparse.Namespace) -> int:
    return list_runs_cmd(args.runs_dir, args.quiet)


def run_verdict(folder: Path) -> str | None:
    """The overall verdict (PASS/FAIL/RE-RUN) stored by a run's check step, None without one,
    "?" when the stored verdict cannot be read (``rig show`` says why)."""
    from rig.errors import StoredResultError
    from rig.steps.check import check_verdict
    from rig.store import RunReader

    reader = RunReader(folder)
    try:
        results = reader.results()
    finally:
        reader.close()
    try:
        verdict = check_verdict(results)
    except StoredResultError:
        return "?"
    return str(verdict.overall) if verdict is not None else None


def list_runs_cmd(runs_dir: Path, quiet: bool) -> int:
    """``rig runs``: one line per run, newest first, with its status and verdict."""
    from rig.store import list_runs

    runs = list_runs(runs_dir)
    if not runs:
        print(f"no runs in {runs_dir}")
        return 0
    width = max(len("RUN"), *(len(r.run_id) for r in runs))
    print(f"{'RUN':<{width}} {'STATUS':<10} {'VERDICT':<7} {'PROCEDURE':<24} DUT")
    for r in runs:
        m = r.meta
        if r.status == "damaged":  # listed, never hiding the others: rig verify RUN says why
            print(f"{r.run_id:<{width}} {'damaged':<10} {'-':<7} (run.sqlite cannot be read)")
            continue
        print(
            f"{r.run_id:<{width}} {r.status:<10} {run_verdict(r.folder) or '-':<7}"
            f" {m.get('procedure', ''):<24} {m.get('dut_serial', '') or '-'}"
        )
    return 0
