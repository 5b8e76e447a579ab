"""``rig runs``: the recorded runs, newest first, with status and verdict."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from rig.cli.common import Parser, Subparsers, add_runs_dir

if TYPE_CHECKING:
    from rig.store.run_store import RunInfo


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
    from rig.store import RunReader
    from rig.verdict import check_verdict

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


def switch_off_after(run: RunInfo) -> None:
    """A run found dead now (its recorder gone; ``run.closed_now``) may have left its outputs on
    when its guardian died too: every output of the run's copy of its rig configuration
    (addresses only) is switched off and read back, one line each on stderr, unless a command
    holds them (a run going on: never touched). Not a run recorded in simulated time: its outputs
    were simulated inside the process that ended, and its addresses name nothing out here."""
    import sys
    import tomllib

    if run.meta.get("clock") == "simulated":
        print(f"rig: {run.run_id} ended without its recorder; it ran in simulated time, so its"
              " outputs ended with it: nothing to switch off", file=sys.stderr)  # fmt: skip
        return

    from rig.config import RigConfig
    from rig.engine.interlock import holders
    from rig.engine.safe_targets import safe_targets
    from rig.engine.switch_off import switch_off_and_confirm

    copy = run.folder / "rig.toml"
    try:
        targets = safe_targets(tomllib.loads(copy.read_text(encoding="utf-8")))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, RecursionError) as exc:
        print(f"rig: warning: {run.run_id} ended without its recorder, and its copy of the rig"
              f" configuration cannot be read ({exc}): run 'rig safe --rig CONFIG.toml'",
              file=sys.stderr)  # fmt: skip
        return
    held = holders(RigConfig(copy, targets.devices))
    if held:
        who = sorted(set(held.values()))
        print(f"rig: {run.run_id} ended without its recorder; its outputs are held by"
              f" {', '.join(who)}, so they are left to it", file=sys.stderr)  # fmt: skip
        return
    states = switch_off_and_confirm(targets.devices, unreachable=list(targets.broken))
    off = [s for s in states.values() if s.off]
    print(f"rig: {run.run_id} ended without its recorder or guardian: its outputs switched off"
          f" and read back ({len(off)} of {len(states)} off)", file=sys.stderr)  # fmt: skip
    for state in states.values():
        if not state.off:
            print(f"rig: error: {state.line()}; run 'rig safe --rig CONFIG.toml' or switch it"
                  " off by hand", file=sys.stderr)  # fmt: skip


def list_runs_cmd(runs_dir: Path, quiet: bool) -> int:
    """``rig runs``: one line per run, newest first, with its status and verdict; a run found
    dead now has its outputs switched off first (:func:`switch_off_after`)."""
    from rig.store import list_runs

    runs = list_runs(runs_dir)
    for r in runs:
        if r.closed_now:
            switch_off_after(r)
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
