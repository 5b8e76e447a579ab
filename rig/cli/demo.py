"""``rig demo``: a shipped procedure on the simulated cage, beside it or in simulated time."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rig.cli.common import Parser, Subparsers, add_runs_dir

if TYPE_CHECKING:
    from rig.procedure.language import Procedure


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    demo = sub.add_parser(
        "demo", parents=parents, help="the acceptance procedure on the simulated cage"
    )
    add_runs_dir(demo)
    demo.add_argument("--procedure", default="dut-acceptance-designed", metavar="PROCEDURE",
                      help="the procedure to run, a file or a shipped name (default: %(default)s,"
                           " the acceptance rig design wrote for the simulated cage: about 60 s of"
                           " cage time; dut-acceptance is its long form, about 155 s)")  # fmt: skip
    demo.add_argument(
        "--simulated-time", action="store_true",
        help="run the simulated cage in this process on simulated time (ADR 0038): as fast as the"
             " computer can, the same data for the same seed on any machine and load; the run"
             " and its report say so. Without it the cage runs beside the rig in real time",
    )  # fmt: skip
    demo.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                      help="set a procedure parameter (as rig run --set)")  # fmt: skip
    demo.add_argument("--sim-config", type=Path, default=None, metavar="SIM.toml",
                      help="simulator configuration (default: the built-in cage)")  # fmt: skip
    demo.set_defaults(func=_cmd_demo)


def _cmd_demo(args: argparse.Namespace) -> int:
    return run_demo(args.runs_dir, args.procedure, args.quiet, simulated_time=args.simulated_time,
                    sim_config=args.sim_config, sets=args.set)  # fmt: skip


def run_demo(runs_dir: Path, procedure: str, quiet: bool, *, simulated_time: bool = False,
             sim_config: Path | None = None, sets: list[str] | None = None) -> int:  # fmt: skip
    """``rig demo``: run a shipped procedure on the simulated cage without prompts; returns the
    run's exit code."""
    import time

    from rig.cli.common import parse_sets
    from rig.cli.run import summarize
    from rig.procedure.language import parse_procedure
    from rig.procedure_files import find_procedure

    t0 = time.monotonic()  # the wall clock: how long the user waited
    proc = parse_procedure(find_procedure(procedure), parse_sets(sets or []))
    runs_dir.mkdir(parents=True, exist_ok=True)
    rig_toml = runs_dir / "sim-rig.toml"
    rig_toml.unlink(missing_ok=True)
    if simulated_time:
        outcome, simulated_s = _in_simulated_time(proc, runs_dir, rig_toml, sim_config, quiet)
    else:
        outcome, simulated_s = (
            _beside_the_simulator(proc, runs_dir, rig_toml, sim_config, quiet),
            None,
        )
    summarize(outcome, quiet)
    if not quiet:
        took = f"demo took {time.monotonic() - t0:.0f} s"
        print(took if simulated_s is None else f"{took} for {simulated_s:.0f} s of simulated time")
    return int(outcome.exit_code)


def _in_simulated_time(proc: Procedure, runs_dir: Path, rig_toml: Path, sim_config: Path | None,
                       quiet: bool) -> tuple[Any, float]:  # fmt: skip
    """The cage in this process, the run and the cage on one simulated clock (ADR 0038)."""
    import timebase
    from rig.cli.run import auto_confirm
    from rig.config import load_rig_config
    from rig.engine.runner import Runner
    from rig.sim_rig import cage_in_process

    with timebase.simulated() as clock, cage_in_process(rig_toml, sim_config) as cage:
        if not quiet:
            print(f"simulated cage in this process, on simulated time; procedure '{proc.title}'"
                  f" ({proc.path.name})")  # fmt: skip
        t0 = clock.monotonic()
        outcome = Runner(proc, load_rig_config(rig_toml), runs_dir, i2c_bus=cage.i2c_bus,
                         confirm=auto_confirm(quiet), quiet=quiet).run()  # fmt: skip
        return outcome, clock.monotonic() - t0


def _beside_the_simulator(proc: Procedure, runs_dir: Path, rig_toml: Path,
                          sim_config: Path | None, quiet: bool) -> Any:  # fmt: skip
    """Start ``rig sim`` as a child process and run on it in real time. A separate process gives
    the simulator its own core, as real instruments have their own electronics. The child dies
    with this process (Linux: the kernel sends it SIGTERM; see rig.child_process), so a killed
    demo leaves no simulator behind."""
    import sys
    import time

    from rig.child_process import start_child, stop_child
    from rig.cli.run import auto_confirm
    from rig.config import load_rig_config
    from rig.engine.runner import Runner
    from rig.errors import UserInputError

    argv = [sys.executable, "-m", "rig.cli", "-q", "sim", "--rig-config", str(rig_toml)]
    if sim_config is not None:
        argv += ["--config", str(sim_config)]
    # Started from the thread that also stops it: the death signal follows the starting thread.
    child = start_child(argv)
    try:
        deadline = time.monotonic() + 30
        while not rig_toml.exists():
            if child.poll() is not None or time.monotonic() > deadline:
                raise UserInputError("the simulated cage did not start; run 'rig sim' to see why")
            time.sleep(0.05)
        cfg = load_rig_config(rig_toml)
        if not quiet:
            print(f"simulated cage running (pid {child.pid}); procedure '{proc.title}'"
                  f" ({proc.path.name})")  # fmt: skip
        return Runner(proc, cfg, runs_dir, confirm=auto_confirm(quiet), quiet=quiet).run()
    finally:
        stop_child(child, wait_s=15.0)  # SIGINT, then SIGKILL after 15 s
