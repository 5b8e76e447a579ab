"""``rig cage``: characterize the cage or set a field, with the safe state on every exit."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import timebase
from rig.cli.common import Parser, Subparsers

if TYPE_CHECKING:
    import threading

    from rig.engine.session import RigSession


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    cage = sub.add_parser(
        "cage",
        parents=parents,
        help="drive the cage: characterize it or set a field (0 0 0 nulls it)",
        description="Cage operations on the devices of a rig configuration (rig sim --rig-config writes one).",
    )
    cage_sub = cage.add_subparsers(dest="cage_command", required=True, parser_class=Parser)
    ch = cage_sub.add_parser(
        "characterize", parents=parents, help="fit B = K I + B0 from a current sweep"
    )
    ch.add_argument("--rig", "--rig-config", dest="rig_config", type=Path, required=True,
                    metavar="FILE.toml", help="the rig configuration (rig sim --rig-config writes one)")  # fmt: skip
    ch.add_argument("--amplitude", type=float, default=1.0, metavar="A", help="sweep current (A)")
    ch.add_argument(
        "--samples", type=int, default=20, metavar="N", help="reference samples per point"
    )
    ch.add_argument("--repeats", type=int, default=2, metavar="R", help="times through the sweep")
    ch.set_defaults(func=_cmd_cage_characterize)
    sf = cage_sub.add_parser("set-field", parents=parents, help="ramp to a field and hold it")
    # Three positionals rather than nargs=3 with a tuple metavar, which argparse (3.11) cannot
    # format: --help and every usage error of set-field used to end in a traceback.
    for axis in "xyz":
        sf.add_argument(f"b{axis}", type=float, metavar=f"B{axis.upper()}",
                        help=f"field {axis} in uT, cage frame")  # fmt: skip
    sf.add_argument("--rig", "--rig-config", dest="rig_config", type=Path, required=True,
                    metavar="FILE.toml", help="the rig configuration (rig sim --rig-config writes one)")  # fmt: skip
    sf.add_argument(
        "--trim", action="store_true", help="close the loop on the reference magnetometer"
    )
    sf.add_argument("--tolerance-nt", type=float, default=10.0, metavar="NT",
                    help="with --trim: how close to the field the reference must read (nT; default: %(default)s)")  # fmt: skip
    sf.add_argument(
        "--hold", type=float, metavar="S", help="hold for S seconds (default: until Ctrl-C)"
    )
    sf.set_defaults(func=_cmd_cage_set_field)
    hd = cage_sub.add_parser(
        "hold", parents=parents,
        help="hold a field, measuring it (inner and outside references); --servo holds it against"
             " the lab field's changes with the trim windings",
    )  # fmt: skip
    for axis in "xyz":
        hd.add_argument(f"b{axis}", type=float, metavar=f"B{axis.upper()}",
                        help=f"field {axis} in uT, cage frame")  # fmt: skip
    hd.add_argument("--rig", "--rig-config", dest="rig_config", type=Path, required=True,
                    metavar="FILE.toml", help="the rig configuration: [cage] ambient and trim needed")  # fmt: skip
    hd.add_argument("--servo", action="store_true",
                    help="feed-forward from the outside reference, feedback from the inner one")  # fmt: skip
    hd.add_argument("--duration", type=float, metavar="S", help="hold for S seconds (default: until Ctrl-C)")  # fmt: skip
    hd.add_argument("--period", type=float, default=0.5, metavar="S",
                    help="servo period (s; default: %(default)s)")  # fmt: skip
    hd.add_argument("--report-s", type=float, default=10.0, metavar="S",
                    help="the rms is of S-second means (default: %(default)s)")  # fmt: skip
    hd.add_argument("--csv", type=Path, metavar="FILE", help="write each period's readings here")
    hd.set_defaults(func=_cmd_cage_hold)


def _cmd_cage_characterize(args: argparse.Namespace) -> int:
    return run_characterize(args.rig_config, args.amplitude, args.samples, args.repeats, args.quiet)


def _cmd_cage_set_field(args: argparse.Namespace) -> int:
    field = [args.bx, args.by, args.bz]
    return run_set_field(
        args.rig_config, field, args.trim, args.tolerance_nt, args.hold, args.quiet
    )


def _cmd_cage_hold(args: argparse.Namespace) -> int:
    from rig.cli.cage_hold import run_hold

    return run_hold(args.rig_config, [args.bx, args.by, args.bz], args.servo, args.duration,
                    args.period, args.report_s, args.csv, args.quiet)  # fmt: skip


def _progress(done: int, total: int) -> None:
    width = 30
    filled = int(width * done / total)
    sys.stderr.write(f"\r  [{'#' * filled}{'.' * (width - filled)}] {done}/{total} points")
    if done == total:
        sys.stderr.write("\n")
    sys.stderr.flush()


def run_characterize(
    rig_config: Path, amplitude_a: float, samples: int, repeats: int, quiet: bool
) -> int:
    """Sweep, fit ``B = K I + B0``, print it, save a new versioned calibration file."""
    from rig.cage.characterize import characterize
    from rig.cli.signals import stop_on_signals
    from rig.config import load_rig_config
    from rig.engine.session import RigSession
    from rig.errors import UserInputError

    cfg = load_rig_config(rig_config)
    if cfg.cage is None or cfg.cage.calibration is None:
        raise UserInputError(
            f"{rig_config}: [cage] needs 'calibration = \"FILE.json\"' to save the result"
        )
    if not 0 < amplitude_a <= min(cfg.cage.max_current_a):
        raise UserInputError(
            f"--amplitude {amplitude_a:g} A must be positive and within the {min(cfg.cage.max_current_a):g} A limit"
        )
    stop = timebase.Event()
    with (
        stop_on_signals(stop, interrupt=True),
        RigSession(cfg, command="rig cage characterize") as rig,
    ):
        controller = rig.cage()
        if not quiet:
            print(f"characterizing the cage: +-{amplitude_a:g} A, {samples} samples per point")
        model = characterize(controller, amplitude_a, samples=samples, repeats=repeats,
                             progress=None if quiet else _progress)  # fmt: skip
        version = model.save(cfg.cage.calibration)
    if not quiet:
        print("K (uT/A, +- 1 sigma):")
        for row, sig in zip(model.k_ut_per_a, model.k_sigma, strict=True):
            print("  " + "  ".join(f"{v:+9.4f} +-{s:.4f}" for v, s in zip(row, sig, strict=True)))
        print(
            "B0 (uT): "
            + "  ".join(
                f"{v:+8.3f} +-{s:.4f}" for v, s in zip(model.b0_ut, model.b0_sigma_ut, strict=True)
            )
        )
        print(
            f"residual rms {model.meta['residual_rms_nt']:.1f} nT; condition number {model.meta['condition_number']:.2f}"
        )
        if again := model.meta["remeasured_points"]:
            print(f"measured again: sweep point(s) {', '.join(str(n + 1) for n in again)}"
                  " (stood out from the fit: a disturbance during the first reading)")  # fmt: skip
        print(f"wrote {version} (and {cfg.cage.calibration})")
    return 0


def run_set_field(rig_config: Path, field_ut: list[float], trim: bool, tolerance_nt: float, hold_s: float | None,
                  quiet: bool) -> int:  # fmt: skip
    """Ramp to a field (optionally trimmed on the reference), hold it, then go safe."""
    import numpy as np

    from drivers.errors import DeviceError
    from rig.cli.signals import stop_on_signals
    from rig.config import load_rig_config
    from rig.engine.session import RigSession
    from rig.errors import RigError

    cfg = load_rig_config(rig_config)
    stop = timebase.Event()
    with stop_on_signals(stop, interrupt=True):
        try:
            with RigSession(cfg, command="rig cage set-field") as rig:
                controller = rig.cage()
                target = np.array(field_ut, float)
                if trim:
                    result = controller.trim(target, tolerance_nt=tolerance_nt)
                    if not quiet:
                        state = "settled" if result.settled else "NOT settled"
                        print(
                            f"trimmed in {result.iterations} iterations: error {result.error_nt:.1f} nT ({state})"
                        )
                    if not result.settled:
                        raise RigError(
                            f"the field did not settle within {tolerance_nt:g} nT; check the reference and the cage calibration"
                        )
                else:
                    currents = controller.set_field(target)
                    if not quiet:
                        print("currents " + ", ".join(f"{c:+.4f} A" for c in currents))
                if not quiet:
                    print(
                        f"holding {np.round(target, 3).tolist()} uT "
                        + ("until Ctrl-C" if hold_s is None else f"for {hold_s:g} s")
                    )
                _hold(rig, hold_s, stop)  # a tripped supply or a hang ends it safely
        except KeyboardInterrupt:
            if not quiet:
                print("interrupted: outputs ramped down and off")
            return 130
        except DeviceError as exc:
            raise RigError(f"{exc} (outputs were sent to their safe state)") from None
    if not quiet:
        print("done: outputs ramped down and off")
    return 0


def _hold(rig: RigSession, seconds: float | None, stop: threading.Event) -> None:
    """Hold the outputs as they are for ``seconds`` (None: until ``stop``), reading the coil
    supplies' protection flags every second; a tripped supply is a fault, raised at once."""
    end = None if seconds is None else timebase.monotonic() + seconds
    next_check = timebase.monotonic()
    while not stop.is_set() and (end is None or timebase.monotonic() < end):
        if timebase.monotonic() >= next_check:
            next_check = timebase.monotonic() + 1.0
            rig.check_coils()
        rig.check()
        until = next_check if end is None else min(next_check, end)
        timebase.wait_any((stop, *rig.interrupts), until - timebase.monotonic())
    rig.check()
