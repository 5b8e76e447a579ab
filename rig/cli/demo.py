"""``rig demo``: the acceptance procedure on the simulated cage."""

from __future__ import annotations

import argparse
from pathlib import Path

from rig.cli.common import Parser, Subparsers, add_runs_dir


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    demo = sub.add_parser(
        "demo", parents=parents, help="the acceptance procedure on the simulated cage"
    )
    add_runs_dir(demo)
    demo.add_argument("--procedure", default="dut-acceptance", metavar="PROCEDURE",
                      help="the procedure to run, a file or a shipped name (default: %(default)s)")  # fmt: skip
    demo.set_defaults(func=_cmd_demo)


def _cmd_demo(args: argparse.Namespace) -> int:
    return run_demo(args.runs_dir, args.procedure, args.quiet)


def run_demo(runs_dir: Path, procedure: str, quiet: bool) -> int:
    """``rig demo``: start ``rig sim`` as a child process, run a shipped procedure on it without
    prompts, stop the simulator. A separate process gives the simulator its own core, as real
    instruments have their own electronics. The child dies with this process (Linux: the kernel
    sends it SIGTERM; see rig.child_process), so a killed demo leaves no simulator behind."""
    import sys
    import time

    from rig.child_process import start_child, stop_child
    from rig.cli.run import auto_confirm, summarize
    from rig.config import load_rig_config
    from rig.engine.runner import Runner
    from rig.errors import UserInputError
    from rig.procedure.language import Procedure, parse_procedure
    from rig.procedure_files import find_procedure

    t0 = time.monotonic()
    proc: Procedure = parse_procedure(find_procedure(procedure))
    runs_dir.mkdir(parents=True, exist_ok=True)
    rig_toml = runs_dir / "sim-rig.toml"
    rig_toml.unlink(missing_ok=True)
    # Started from the thread that also stops it: the death signal follows the starting thread.
    child = start_child(
        [sys.executable, "-m", "rig.cli", "-q", "sim", "--rig-config", str(rig_toml)]
    )
    try:
        deadline = time.monotonic() + 30
        while not rig_toml.exists():
            if child.poll() is not None or time.monotonic() > deadline:
                raise UserInputError("the simulated cage did not start; run 'rig sim' to see why")
            time.sleep(0.05)
        cfg = load_rig_config(rig_toml)
        if not quiet:
            print(
                f"simulated cage running (pid {child.pid}); procedure '{proc.title}' ({proc.path.name})"
            )
        outcome = Runner(proc, cfg, runs_dir, confirm=auto_confirm(quiet), quiet=quiet).run()
    finally:
        stop_child(child, wait_s=15.0)  # SIGINT, then SIGKILL after 15 s
    summarize(outcome, quiet)
    if not quiet:
        print(f"demo took {time.monotonic() - t0:.0f} s")
    return outcome.exit_code
