"""``rig report``: (re)build a run's HTML and PDF report."""

from __future__ import annotations

import argparse
from pathlib import Path

from rig.cli.common import Parser, Subparsers, add_run, add_runs_dir, resolve_run


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    rep = sub.add_parser("report", parents=parents, help="(re)build a run's HTML and PDF report")
    add_run(rep)
    add_runs_dir(rep)
    rep.set_defaults(func=_cmd_report)


def _cmd_report(args: argparse.Namespace) -> int:
    return report_run(args.run, args.runs_dir, args.quiet)


def report_run(run: str, runs_dir: Path, quiet: bool) -> int:
    """``rig report``: (re)build the HTML and PDF report of a run."""
    from rig.report.acceptance import build_report

    html_path, pdf_path = build_report(resolve_run(run, runs_dir))
    if not quiet:
        print(f"wrote {html_path}\nwrote {pdf_path}")
    return 0
