"""``rig export``: a run as CSV files or one HDF5 file."""

from __future__ import annotations

import argparse
from pathlib import Path

from rig.cli.common import Parser, Subparsers, add_run, add_runs_dir, resolve_run


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    exp = sub.add_parser("export", parents=parents, help="export a run to CSV or HDF5")
    add_run(exp)
    exp.add_argument("--format", choices=("csv", "hdf5"), default="csv",
                     help="csv: one file per table; hdf5: one run.h5 (default: %(default)s)")  # fmt: skip
    exp.add_argument("--out", type=Path, metavar="PATH",
                     help="where to write (default: csv/ or run.h5 in the run folder)")  # fmt: skip
    add_runs_dir(exp)
    exp.set_defaults(func=_cmd_export)


def _cmd_export(args: argparse.Namespace) -> int:
    return export_run(args.run, args.runs_dir, args.format, args.out)


def export_run(run: str, runs_dir: Path, fmt: str, out: Path | None) -> int:
    """``rig export``."""
    from rig.store import RunReader
    from rig.store.export import export_csv, export_hdf5
    from rig.store.seal import record_written

    folder = resolve_run(run, runs_dir)
    reader = RunReader(folder)
    try:
        if fmt == "csv":
            files = export_csv(reader, out or folder / "csv")
            print(f"wrote {len(files)} files to {files[0].parent}")
        else:
            files = [export_hdf5(reader, out or folder / "run.h5")]
            print(f"wrote {files[0]}")
    finally:
        reader.close()
    record_written(folder, files, "rig export")  # those inside the run folder: verify knows them
    return 0
