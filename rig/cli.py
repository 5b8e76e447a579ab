"""The ``rig`` command.

Exit codes: 0 success, 1 unexpected internal error, 2 bad input or a calibration the data cannot
support (one line on stderr naming the problem and the fix), 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from drivers.errors import DeviceError
from rig import __version__
from rig.errors import RigError, UserInputError

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


class _Parser(argparse.ArgumentParser):
    """argparse with the project's one-line error and exit code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_INPUT, f"rig: {message} (see '{self.prog} --help')\n")


def _columns(text: str) -> list[str]:
    return [c.strip() for c in text.split(",") if c.strip()]


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    parser = _Parser(prog="rig", description="Helmholtz-cage magnetometer test rig.")
    parser.add_argument("--version", action="version", version=f"rig {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-q", "--quiet", action="store_true", help="print errors only")
    verbosity.add_argument(
        "-v", "--verbose", action="store_true", help="more detail, tracebacks on internal errors"
    )
    # -q/-v are accepted before or after the subcommand (``rig -q sim`` and ``rig sim -q``).
    common = _Parser(add_help=False)
    common_v = common.add_mutually_exclusive_group()
    common_v.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                          help="print errors only")  # fmt: skip
    common_v.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                          help="more detail, tracebacks on internal errors")  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    cal = sub.add_parser(
        "calibrate",
        parents=[common],
        help="fit scale, offset, misalignment and current-to-bias to a CSV file",
        description=(
            "Fit m = T h + o + sum_j k_j u_j to recorded data. --field gives a vector (cage)"
            " calibration, --field-magnitude an attitude-independent (scalar) one. Any consistent"
            " field unit works; results are labelled uT."
        ),
    )
    cal.add_argument(
        "data",
        type=Path,
        metavar="DATA.csv|RUN",
        help="CSV file with a header row, a run folder, or a run id under --runs-dir",
    )
    cal.add_argument(
        "--runs-dir",
        type=Path,
        default=Path("runs"),
        metavar="DIR",
        help="where to look for a run id (default: runs)",
    )
    cal.add_argument(
        "--measured", type=_columns, metavar="COLX,COLY,COLZ",
        help="raw DUT reading columns",
    )  # fmt: skip
    ref = cal.add_mutually_exclusive_group()
    ref.add_argument(
        "--field", type=_columns, metavar="COLX,COLY,COLZ",
        help="reference field vector columns (vector calibration)",
    )  # fmt: skip
    ref.add_argument(
        "--field-magnitude", metavar="COL", help="reference field magnitude column (scalar)"
    )
    cal.add_argument(
        "--telemetry", type=_columns, default=[], metavar="COL1,COL2,...",
        help="telemetry channels (currents) whose bias to fit",
    )  # fmt: skip
    cal.add_argument(
        "--method",
        choices=("ml", "twostep", "centered", "ellipsoid", "vector", "centered-seq", "ekf", "ukf"),
        help="estimator (default: vector with --field, ml with --field-magnitude); centered-seq,"
        " ekf and ukf are the sequential (real-time) filters, run over the rows in file order",
    )
    cal.add_argument(
        "--filter-variant",
        choices=("energy", "paper", "paper-augmented"),
        default="energy",
        help="ekf/ukf form: energy (default, converges from a zero start), paper (Crassidis et al."
        " as published), paper-augmented (12-state UKF)",
    )
    cal.add_argument(
        "--backend",
        choices=("numpy", "filterpy"),
        default="numpy",
        help="filter implementation (filterpy runs the paper variants)",
    )
    cal.add_argument(
        "--history", type=Path, metavar="HISTORY.csv",
        help="write the filter's estimate and 1-sigma per parameter as it converges (CSV)",
    )  # fmt: skip
    cal.add_argument(
        "--noise-nt", type=float, metavar="SIGMA",
        help="raw noise per axis, 1-sigma in nT: the chi-square test and Cramer-Rao bound use it",
    )  # fmt: skip
    cal.add_argument(
        "--robust", choices=("huber", "bisquare"), help="reweight against outliers (ml, vector)"
    )
    cal.add_argument("--out", type=Path, metavar="RESULT.json", help="write the result file")
    cal.add_argument(
        "--c-header", type=Path, metavar="FILE.h", help="write a C header for flight software"
    )
    cal.set_defaults(func=_cmd_calibrate)

    sim = sub.add_parser(
        "sim",
        parents=[common],
        help="run the simulated cage (Modbus, serial and I2C devices on loopback)",
        description=(
            "Start the physics-based simulated cage behind the real wire protocols and keep it"
            " running until Ctrl-C or SIGTERM. Listens on loopback and pseudo-terminals only."
        ),
    )
    sim.add_argument(
        "--config", metavar="SIM.toml", help="simulator configuration (default: built-in cage)"
    )
    sim.add_argument(
        "--endpoints-json", type=Path, metavar="FILE", help="write the device endpoints as JSON"
    )
    sim.add_argument(
        "--rig-config",
        type=Path,
        metavar="FILE.toml",
        help="write a rig configuration for the devices",
    )
    sim.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    sim.set_defaults(func=_cmd_sim)

    runp = sub.add_parser("run", parents=[common], help="run a procedure on the rig")
    runp.add_argument(
        "procedure", metavar="PROCEDURE", help="a .yaml file or a shipped procedure name"
    )
    runp.add_argument(
        "--rig", type=Path, required=True, metavar="CONFIG.toml", help="rig configuration"
    )
    runp.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE", help="set a procedure parameter"
    )
    runp.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR")
    runp.add_argument(
        "--yes", action="store_true", help="confirm operator prompts automatically (recorded)"
    )
    runp.set_defaults(func=_cmd_run)
    safe = sub.add_parser(
        "safe", parents=[common], help="switch every supply, load and relay of the rig off now"
    )
    safe.add_argument(
        "--rig", type=Path, required=True, metavar="CONFIG.toml", help="rig configuration"
    )
    safe.set_defaults(func=_cmd_safe)
    chk = sub.add_parser(
        "check", parents=[common], help="dry-run a procedure: timeline, duration, limits"
    )
    chk.add_argument("procedure", metavar="PROCEDURE")
    chk.add_argument(
        "--rig",
        type=Path,
        metavar="CONFIG.toml",
        help="check currents and fields against its limits",
    )
    chk.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    chk.set_defaults(func=_cmd_check)
    demo = sub.add_parser(
        "demo", parents=[common], help="the acceptance procedure on the simulated cage"
    )
    demo.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR")
    demo.add_argument("--procedure", default="dut-acceptance", metavar="PROCEDURE")
    demo.set_defaults(func=_cmd_demo)
    runs = sub.add_parser("runs", parents=[common], help="list recorded runs")
    runs.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR")
    runs.set_defaults(func=_cmd_runs)
    show = sub.add_parser("show", parents=[common], help="summarize one run (--json: all of it)")
    show.add_argument("run", metavar="RUN")
    show.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR")
    show.add_argument(
        "--json",
        action="store_true",
        help="print everything stored (meta, samples, steps, results) as one JSON document",
    )
    show.set_defaults(func=_cmd_show)
    rep = sub.add_parser("report", parents=[common], help="(re)build a run's HTML and PDF report")
    rep.add_argument("run", metavar="RUN")
    rep.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR")
    rep.set_defaults(func=_cmd_report)
    ver = sub.add_parser(
        "verify",
        parents=[common],
        help="check that a run folder is as it was sealed (data, configuration, reports)",
        description="Recompute the run's data SHA-256 and compare it with the seal written when"
        " the run closed, the sealed procedure and rig configuration copies, and the digest every"
        " report states. Exit 0 when intact, 1 when anything changed or the run is not sealed.",
    )
    ver.add_argument("run", metavar="RUN", help="run folder or run id")
    ver.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR",
                     help="where run ids are looked up (default: runs)")  # fmt: skip
    ver.set_defaults(func=_cmd_verify)
    exp = sub.add_parser("export", parents=[common], help="export a run to CSV or HDF5")
    exp.add_argument("run", metavar="RUN")
    exp.add_argument("--format", choices=("csv", "hdf5"), default="csv")
    exp.add_argument("--out", type=Path, metavar="PATH")
    exp.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR")
    exp.set_defaults(func=_cmd_export)

    cage = sub.add_parser(
        "cage",
        parents=[common],
        help="drive the cage: characterize it, set or null a field",
        description="Cage operations on the devices of a rig configuration (rig sim --rig-config writes one).",
    )
    cage_sub = cage.add_subparsers(dest="cage_command", required=True, parser_class=_Parser)
    ch = cage_sub.add_parser(
        "characterize", parents=[common], help="fit B = K I + B0 from a current sweep"
    )
    ch.add_argument("--rig-config", type=Path, required=True, metavar="FILE.toml")
    ch.add_argument("--amplitude", type=float, default=1.0, metavar="A", help="sweep current (A)")
    ch.add_argument(
        "--samples", type=int, default=20, metavar="N", help="reference samples per point"
    )
    ch.add_argument("--repeats", type=int, default=2, metavar="R", help="times through the sweep")
    ch.set_defaults(func=_cmd_cage_characterize)
    sf = cage_sub.add_parser("set-field", parents=[common], help="ramp to a field and hold it")
    sf.add_argument(
        "field", type=float, nargs=3, metavar=("BX", "BY", "BZ"), help="field in uT, cage frame"
    )
    sf.add_argument("--rig-config", type=Path, required=True, metavar="FILE.toml")
    sf.add_argument(
        "--trim", action="store_true", help="close the loop on the reference magnetometer"
    )
    sf.add_argument("--tolerance-nt", type=float, default=10.0, metavar="NT")
    sf.add_argument(
        "--hold", type=float, metavar="S", help="hold for S seconds (default: until Ctrl-C)"
    )
    sf.set_defaults(func=_cmd_cage_set_field)

    ex = sub.add_parser(
        "example-data",
        parents=[common],
        help="write a synthetic data set with known truth",
        description=(
            "rax: a tumbling CubeSat with four panel currents and EPS beacons (scalar); cage: a"
            " Helmholtz-cage sweep with two load channels (vector)."
        ),
    )
    ex.add_argument("out", type=Path, metavar="OUT.csv")
    ex.add_argument("--kind", choices=("rax", "cage"), default="rax")
    ex.add_argument("--samples", type=int, default=6000, metavar="N")
    ex.add_argument("--seed", type=int, default=1)
    ex.add_argument("--noise-nt", type=float, default=100.0, metavar="SIGMA")
    ex.set_defaults(func=_cmd_example_data)
    return parser


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from rig.calibration import Samples
    from rig.io.csv_table import read_columns

    if args.data.is_dir():
        return _calibrate_run(args)
    if not args.data.exists():
        run_folder = args.runs_dir / args.data
        if (run_folder / "run.sqlite").exists():
            args.data = run_folder
            return _calibrate_run(args)
        if args.data.suffix.lower() != ".csv":
            raise UserInputError(
                f"no CSV file or run '{args.data}' (looked at {args.data} and {run_folder}):"
                " give a CSV file, a run folder, or a run id listed by 'rig runs' (--runs-dir DIR)"
            )
    if args.measured is None:
        raise UserInputError("--measured COLX,COLY,COLZ is required for a CSV file")
    if args.field is None and args.field_magnitude is None:
        raise UserInputError(
            "give --field COLX,COLY,COLZ (vector) or --field-magnitude COL (scalar)"
        )
    if len(args.measured) != 3:
        raise UserInputError(f"--measured needs three columns X,Y,Z, got {len(args.measured)}")
    if args.field is not None and len(args.field) != 3:
        raise UserInputError(f"--field needs three columns X,Y,Z, got {len(args.field)}")
    if len(set(args.telemetry)) != len(args.telemetry):
        raise UserInputError("--telemetry names a column twice: list each channel once")
    wanted = list(args.measured) + (args.field or [args.field_magnitude]) + list(args.telemetry)
    cols = read_columns(args.data, list(dict.fromkeys(wanted)))
    import numpy as np

    measured = np.column_stack([cols[c] for c in args.measured])
    telemetry = np.column_stack([cols[c] for c in args.telemetry]) if args.telemetry else None
    if args.field is not None:
        samples = Samples.build(
            measured,
            field_ut=np.column_stack([cols[c] for c in args.field]),
            telemetry=telemetry,
            channels=tuple(args.telemetry),
        )
    else:
        samples = Samples.build(
            measured,
            field_magnitude_ut=cols[args.field_magnitude],
            telemetry=telemetry,
            channels=tuple(args.telemetry),
        )
    return _fit_and_emit(samples, args)


def _fit_and_emit(samples: Any, args: argparse.Namespace) -> int:
    """Fit, write the result file and C header if asked, print the table."""
    from rig.calibration import calibrate
    from rig.calibration.export_c import c_header
    from rig.calibration.realtime import FilterOptions
    from rig.report.tables import calibration_table

    filter_methods = ("centered-seq", "ekf", "ukf")
    if args.history is not None and args.method not in filter_methods:
        raise UserInputError("--history needs a filter: add --method centered-seq, ekf or ukf")
    opts = None
    if args.method in filter_methods:
        opts = FilterOptions(args.method, args.filter_variant, args.backend)
    result = calibrate(
        samples, args.method, noise_nt=args.noise_nt, robust=args.robust, filter_options=opts
    )
    if args.history is not None and result.history is not None:
        _write(args.history, _history_csv(result))
    if args.out is not None:
        _write(args.out, json.dumps(result.to_dict(), indent=2) + "\n")
    if args.c_header is not None:
        _write(args.c_header, c_header(result, prefix=args.c_header.stem, source=str(args.data)))
    if not args.quiet:
        print(calibration_table(result, source=str(args.data), verbose=args.verbose))
        for path in (args.out, args.c_header, args.history):
            if path is not None:
                print(f"wrote {path}")
    return EXIT_OK


def _history_csv(result: Any) -> str:
    """The filter history as CSV: sample number, every parameter, then every 1-sigma."""
    import io

    import numpy as np

    from rig.calibration.realtime import history_table

    header, body = history_table(result.history, result.names)
    buf = io.StringIO()
    buf.write(",".join(header) + "\n")
    np.savetxt(buf, body, delimiter=",", fmt="%.9g")
    return buf.getvalue()


def _calibrate_run(args: argparse.Namespace) -> int:
    """Re-fit the DUT from a stored run (its procedure's magnetometers and loads by default);
    ``--method ml`` (or another scalar method) fits attitude-independently from the same data."""
    from rig.engine.analysis import stored_run_data
    from rig.store import RunReader

    reader = RunReader(args.data)
    try:
        telemetry = list(args.telemetry) if args.telemetry else list(reader.meta().get("loads", []))
        samples, _ = stored_run_data(reader, telemetry)
    finally:
        reader.close()
    return _fit_and_emit(samples, args)


def _write(path: Path, text: str) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise UserInputError(f"cannot write {path}: {exc.strerror}: choose another path") from None


def _cmd_sim(args: argparse.Namespace) -> int:
    from rig.sim_command import run_sim

    return run_sim(args.config, args.endpoints_json, args.rig_config, args.duration, args.quiet)


def _cmd_run(args: argparse.Namespace) -> int:
    from rig.run_commands import run_procedure

    return run_procedure(args.procedure, args.rig, args.set, args.runs_dir, args.yes, args.quiet)


def _cmd_check(args: argparse.Namespace) -> int:
    from rig.run_commands import run_check

    return run_check(args.procedure, args.rig, args.set, args.quiet)


def _cmd_demo(args: argparse.Namespace) -> int:
    from rig.run_commands import run_demo

    return run_demo(args.runs_dir, args.procedure, args.quiet)


def _cmd_safe(args: argparse.Namespace) -> int:
    from rig.engine.guardian import safe_outputs

    done, problems = safe_outputs(args.rig)
    if not args.quiet:
        print(f"switched off: {', '.join(done) or 'nothing'}")
    for p in problems:
        print(f"rig: error: could not switch off {p}; switch it off by hand", file=sys.stderr)
    return EXIT_INPUT if problems else EXIT_OK


def _cmd_runs(args: argparse.Namespace) -> int:
    from rig.run_commands import list_runs_cmd

    return list_runs_cmd(args.runs_dir, args.quiet)


def _cmd_show(args: argparse.Namespace) -> int:
    from rig.run_commands import show_run

    return show_run(args.run, args.runs_dir, args.json)


def _cmd_report(args: argparse.Namespace) -> int:
    from rig.run_commands import report_run

    return report_run(args.run, args.runs_dir, args.quiet)


def _cmd_verify(args: argparse.Namespace) -> int:
    from rig.run_commands import resolve_run
    from rig.verify_command import verify

    return verify(resolve_run(args.run, args.runs_dir), args.quiet)


def _cmd_export(args: argparse.Namespace) -> int:
    from rig.run_commands import export_run

    return export_run(args.run, args.runs_dir, args.format, args.out)


def _cmd_cage_characterize(args: argparse.Namespace) -> int:
    from rig.cage_command import run_characterize

    return run_characterize(args.rig_config, args.amplitude, args.samples, args.repeats, args.quiet)


def _cmd_cage_set_field(args: argparse.Namespace) -> int:
    from rig.cage_command import run_set_field

    return run_set_field(
        args.rig_config, args.field, args.trim, args.tolerance_nt, args.hold, args.quiet
    )


def _cmd_example_data(args: argparse.Namespace) -> int:
    from rig.calibration.synthetic import cage_like, rax_like
    from rig.io.csv_table import write_columns

    if args.samples < 100:
        raise UserInputError(f"--samples must be at least 100, got {args.samples}")
    noise_ut = args.noise_nt / 1000.0
    if args.kind == "rax":
        case = rax_like(args.samples, seed=args.seed, noise_ut=noise_ut)
        s = case.samples
        cols = {"time_s": case.time_s}
        cols |= {f"m{ax}_ut": s.measured_ut[:, i] for i, ax in enumerate("xyz")}
        cols["b_ut"] = s.field_magnitude_ut
        cols |= {ch: s.telemetry[:, j] for j, ch in enumerate(s.channels)}
        hint = "--measured mx_ut,my_ut,mz_ut --field-magnitude b_ut --telemetry " + ",".join(
            s.channels
        )
    else:
        case = cage_like(args.samples, seed=args.seed, noise_ut=noise_ut)
        s = case.samples
        cols = {"time_s": case.time_s}
        cols |= {f"m{ax}_ut": s.measured_ut[:, i] for i, ax in enumerate("xyz")}
        cols |= {f"h{ax}_ut": case.field_ut[:, i] for i, ax in enumerate("xyz")}
        cols |= {ch: s.telemetry[:, j] for j, ch in enumerate(s.channels)}
        hint = "--measured mx_ut,my_ut,mz_ut --field hx_ut,hy_ut,hz_ut --telemetry " + ",".join(
            s.channels
        )
    write_columns(args.out, cols)
    if not args.quiet:
        print(f"wrote {args.out}: {args.samples} samples ({args.kind}); calibrate it with")
        print(f"  rig calibrate {args.out} {hint} --noise-nt {args.noise_nt:g}")
    return EXIT_OK


def _stoppable() -> None:
    """Ctrl-C (SIGINT) always stops the rig, even when a non-interactive shell started it in the
    background with SIGINT ignored (the shell's convention): a run that cannot be interrupted is
    worse than a script that has to say so."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


EXIT_CLOSED_PIPE = 128 + 13
"""Like a tool killed by SIGPIPE: the reader of our output (``| head``) has gone."""


def _stdout_closed() -> bool:
    """True when standard output is a pipe whose reader has gone."""
    import select

    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # replaced by a test's capture, or closed
        return False
    poll = select.poll()
    poll.register(fd, select.POLLOUT)
    return any(ev & select.POLLERR for _, ev in poll.poll(0))


def _quiet_exit_on_closed_pipe() -> int:
    """Point stdout at /dev/null so that the interpreter's final flush cannot fail again, and
    exit without a word (the reader chose to stop reading)."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return EXIT_CLOSED_PIPE


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``rig`` command; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)  # --help on a closed pipe: argparse drops the text itself
    _stoppable()
    try:
        code: int = args.func(args)
        sys.stdout.flush()  # inside the try: a closed pipe shows up here for short outputs
        return code
    except BrokenPipeError as exc:
        if _stdout_closed():
            return _quiet_exit_on_closed_pipe()
        return _internal_error(exc, args.verbose)
    except (RigError, DeviceError) as exc:
        print(f"rig: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("rig: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:
        return _internal_error(exc, args.verbose)


def _internal_error(exc: Exception, verbose: bool) -> int:
    """A bug: one line unless the user asked for the traceback."""
    if verbose:
        raise exc
    print(
        f"rig: internal error: {type(exc).__name__}: {exc} (rerun with -v for the traceback"
        " and report it)",
        file=sys.stderr,
    )
    return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
