"""``rig run``: execute a procedure on the rig a configuration names; the run summary."""

from __future__ import annotations

import argparse
import contextlib
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rig.cli.common import Parser, Subparsers, add_runs_dir, criterion_value, parse_sets
from rig.errors import UserInputError

if TYPE_CHECKING:
    from rig.steps.vocabulary import Procedure


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    runp = sub.add_parser("run", parents=parents, help="run a procedure on the rig")
    runp.add_argument(
        "procedure", metavar="PROCEDURE", help="a .yaml file or a shipped procedure name"
    )
    runp.add_argument(
        "--rig", type=Path, required=True, metavar="CONFIG.toml", help="rig configuration"
    )
    runp.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE", help="set a procedure parameter"
    )
    add_runs_dir(runp)
    runp.add_argument(
        "--yes", action="store_true", help="confirm operator prompts automatically (recorded)"
    )
    runp.add_argument(
        "--serve", action="store_true",
        help="also serve the web page on this machine, to watch and operate the run (rig serve)",
    )  # fmt: skip
    runp.add_argument(
        "--port", type=int, default=None, metavar="N",
        help="port of the --serve page (default 8765; 0 picks a free one)",
    )  # fmt: skip
    runp.set_defaults(func=_cmd_run)


def _cmd_run(args: argparse.Namespace) -> int:
    if args.port is not None and not args.serve:
        raise UserInputError("--port is the port of the --serve page: add --serve")
    if not args.serve:
        return run_procedure(args.procedure, args.rig, args.set, args.runs_dir, args.yes,
                             args.quiet)  # fmt: skip
    with page_server(args.runs_dir, args.rig, args.port, args.quiet) as url:
        return run_procedure(args.procedure, args.rig, args.set, args.runs_dir, args.yes,
                             args.quiet, page_url=url)  # fmt: skip


@contextlib.contextmanager
def page_server(runs_dir: Path, rig_config: Path, port: int | None, quiet: bool) -> Iterator[str]:
    """``rig serve`` as a child process for as long as the run lasts; yields its address."""
    from rig.child_process import start_child, stop_child
    from rig.cli.serve import DEFAULT_PORT

    runs_dir.mkdir(parents=True, exist_ok=True)
    argv = [sys.executable, "-m", "rig.cli", "-q", "serve", "--runs-dir", str(runs_dir),
            "--rig", str(rig_config), "--port", str(DEFAULT_PORT if port is None else port)]  # fmt: skip
    child = start_child(argv, stdout=subprocess.PIPE)
    assert child.stdout is not None
    line = child.stdout.readline().decode(errors="replace").strip()
    if not line.startswith("rig serve: "):
        stop_child(child, first=signal.SIGTERM, wait_s=2.0)
        raise UserInputError("the --serve page did not start (see the line above); choose"
                             " another --port, or run without --serve")  # fmt: skip
    url = line.removeprefix("rig serve: ")
    print(f"rig: watch and operate this run at {url}", file=sys.stderr, flush=True)
    try:
        yield url
    finally:
        stop_child(child, first=signal.SIGTERM, wait_s=3.0)


def confirm_all(text: str) -> bool:
    print(f"[auto-confirmed] {text}")
    return True


def confirm_all_quietly(text: str) -> bool:
    return True  # the run records every prompt and that it was confirmed


def auto_confirm(quiet: bool) -> Callable[[str], bool]:
    """The operator-prompt answer of ``--yes`` (and ``rig demo``): yes, said aloud unless quiet."""
    return confirm_all_quietly if quiet else confirm_all


def summarize(outcome: Any, quiet: bool) -> None:
    """A short terminal summary of a finished run. With ``quiet`` only a run that did not complete
    says so: one line on stderr with its status and reason (``-q`` means errors only, not nothing)."""
    from rig.store.run_states import RunStatus
    from rig.verdict import check_verdict  # here: building the parser stays light

    verdict = check_verdict(outcome.results)
    if quiet:
        if outcome.status != RunStatus.COMPLETE:
            failed = verdict.failed if verdict is not None else []
            what = (
                f" ({', '.join(failed)})" if outcome.status == RunStatus.FAILED and failed else ""
            )
            prefix = "error: " if outcome.status == RunStatus.ERROR else ""
            safe = (
                "; every output read back off"
                if outcome.outputs.startswith("outputs: read back off")
                else ""
            )
            print(
                f"rig: {prefix}run {outcome.folder.name} ended with status {outcome.status}:"
                f" {outcome.reason}{what}{safe}; data in {outcome.folder}",
                file=sys.stderr,
            )
        return
    print(f"run {outcome.folder.name}: {outcome.status} ({outcome.reason})")
    if outcome.outputs:
        print(outcome.outputs)
    if verdict is not None:
        for row in verdict.criteria:
            print(f"  {row.verdict:<4} {row.name:<28} {criterion_value(row)}")
        print(f"VERDICT: {verdict.overall}")
    reports = [outcome.folder / n for n in ("report.html", "report.pdf")]
    for path in reports:
        if path.exists():
            print(f"report: {path}")
    if not any(p.exists() for p in reports):
        print(f"report: not written; write it with: rig report {outcome.folder}")
    print(f"data:   {outcome.folder / 'run.sqlite'}")


def refuse_unanswerable_questions(proc: Procedure) -> None:
    """A one-line :class:`UserInputError` before anything starts when a step asks the operator
    and nothing could answer (no terminal on stdin, no page, no --yes): the run would stop there
    with its outputs already on."""
    from rig.steps import KINDS

    for step in proc.steps:
        if KINDS[step.kind].asks_operator:
            raise UserInputError(
                f"{step.where}: step {step.index + 1} ({step.kind}) asks the operator a question"
                " and the input is not a terminal: run in a terminal, answer on the page"
                " ('rig run --serve'), or pass --yes to confirm every question"
            )


def run_procedure(
    procedure: str,
    rig_config: Path,
    sets: list[str],
    runs_dir: Path,
    yes: bool,
    quiet: bool,
    page_url: str | None = None,
) -> int:
    """``rig run``: execute on the rig named by the configuration."""
    from rig.config import load_rig_config
    from rig.engine.runner import Runner
    from rig.procedure.language import parse_procedure
    from rig.procedure_files import find_procedure

    proc = parse_procedure(find_procedure(procedure), parse_sets(sets))
    cfg = load_rig_config(rig_config)
    confirm = auto_confirm(quiet) if yes else None
    if confirm is None and page_url is None and not sys.stdin.isatty():
        refuse_unanswerable_questions(proc)
    runner = Runner(proc, cfg, runs_dir, confirm=confirm, quiet=quiet, page_url=page_url)
    outcome = runner.run()
    summarize(outcome, quiet)
    return outcome.exit_code
