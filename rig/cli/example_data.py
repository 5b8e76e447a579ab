"""``rig example-data``: a synthetic data set with known truth, ready for ``rig calibrate``."""

from __future__ import annotations

import argparse
from pathlib import Path

from rig.cli.common import EXIT_OK, Parser, Subparsers, write_text
from rig.errors import UserInputError


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    ex = sub.add_parser(
        "example-data",
        parents=parents,
        help="write a synthetic data set with known truth",
        description=(
            "rax: a tumbling CubeSat with four panel currents and EPS beacons (scalar); cage: a"
            " Helmholtz-cage sweep with two load channels (vector)."
        ),
    )
    ex.add_argument("out", type=Path, metavar="OUT.csv", help="the CSV file to write")
    ex.add_argument("--kind", choices=("rax", "cage"), default="rax",
                    help="which data set (default: %(default)s; see above)")  # fmt: skip
    ex.add_argument("--samples", type=int, default=6000, metavar="N",
                    help="rows to write (default: %(default)s)")  # fmt: skip
    ex.add_argument("--seed", type=int, default=1,
                    help="random seed: the same seed gives the same data (default: %(default)s)")  # fmt: skip
    ex.add_argument("--noise-nt", type=float, default=100.0, metavar="SIGMA",
                    help="magnetometer noise per axis (nT, 1 sigma; default: %(default)s)")  # fmt: skip
    ex.set_defaults(func=_cmd_example_data)


def _cmd_example_data(args: argparse.Namespace) -> int:
    from rig.calibration.synthetic import cage_like, rax_like
    from rig.io.csv_table import columns_text

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
    write_text(args.out, columns_text(cols))
    if not args.quiet:
        print(f"wrote {args.out}: {args.samples} samples ({args.kind}); calibrate it with")
        print(f"  rig calibrate {args.out} {hint} --noise-nt {args.noise_nt:g}")
    return EXIT_OK
