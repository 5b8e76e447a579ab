"""``rig lab``: the lab index (PostgreSQL) of every rig's closed runs: sync, runs, dut, trend,
audit. See docs/lab.md; nothing here is needed by a rig without a lab index."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from rig.cli.common import Parser, Subparsers
from rig.errors import UserInputError

NO_URL = (
    "no lab index configured: give --lab postgresql://USER@HOST:PORT/DB, set RIG_LAB_URL, or"
    " write [lab] url in the rig configuration (--rig CONFIG.toml); see docs/lab.md"
)


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    lab = sub.add_parser(
        "lab", parents=parents, help="the lab index: runs of every rig in one PostgreSQL database",
        description="The lab index (PostgreSQL) of every rig's closed runs; see docs/lab.md.",
    )  # fmt: skip
    common = Parser(add_help=False)
    common.add_argument("--lab", metavar="URL", default=None,
                        help="postgresql://USER@HOST:PORT/DB (default: $RIG_LAB_URL, else [lab] url"
                             " of --rig); the password comes from ~/.pgpass or PGPASSWORD")  # fmt: skip
    common.add_argument("--rig", type=Path, metavar="CONFIG.toml", default=None,
                        help="rig configuration whose [lab] url names the index")  # fmt: skip
    common.add_argument("--json", action="store_true", help="JSON rows instead of a table")
    cmds = lab.add_subparsers(dest="lab_command", required=True, parser_class=Parser)
    both = [*parents, common]

    sync = cmds.add_parser("sync", parents=both, help="push every closed run not yet in the index")
    sync.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR",
                      help="the runs folder to push (default: runs)")  # fmt: skip
    sync.set_defaults(func=_cmd_sync)

    runs = cmds.add_parser("runs", parents=both, help="the newest runs of every rig")
    runs.add_argument("--dut", metavar="SERIAL", help="only this DUT serial")
    runs.add_argument("--status", metavar="S", help="only this status (complete, failed, ...)")
    runs.add_argument("--limit", type=int, default=50, metavar="N", help="at most N runs (50)")
    runs.set_defaults(func=_cmd_runs)

    dut = cmds.add_parser("dut", parents=both, help="every acceptance of one DUT serial")
    dut.add_argument("serial", metavar="SERIAL", help="the DUT serial, e.g. SN-0042")
    dut.set_defaults(func=_cmd_dut)

    trend = cmds.add_parser("trend", parents=both,
                            help="a calibration parameter over runs, with control limits per lot")  # fmt: skip
    trend.add_argument("param", metavar="PARAM",
                       help="a calibration result name: x0_ut, y0_ut, z0_ut, a, b, c, rho_deg,"
                            " phi_deg, lambda_deg, residual_rms_nt")  # fmt: skip
    trend.add_argument("--lot", metavar="L", help="only this lot (the procedure parameter 'lot')")
    trend.add_argument("--png", type=Path, metavar="FILE", help="also plot it to this PNG")
    trend.set_defaults(func=_cmd_trend)

    audit = cmds.add_parser("audit", parents=both,
                            help="expired certificates, unsealed and refused runs, which rig has"
                                 " the outliers")  # fmt: skip
    audit.set_defaults(func=_cmd_audit)


def _url(args: argparse.Namespace) -> str:
    from rig.lab.url import resolve_url

    raw: dict[str, Any] | None = None
    if args.rig is not None:
        from rig.config import load_rig_config

        raw = load_rig_config(args.rig).raw
    url = resolve_url(args.lab, raw, args.rig)
    if url is None:
        raise UserInputError(NO_URL)
    return url


def _query(args: argparse.Namespace) -> Any:
    """An open connection to the index, at the newest schema (the caller closes it)."""
    from rig.lab.schema import open_index

    return open_index(_url(args))


def _emit(args: argparse.Namespace, rows: Any, text: str) -> None:
    print(json.dumps(rows, indent=1, default=str) if args.json else text)


def _cmd_sync(args: argparse.Namespace) -> int:
    from rig.lab.sync import check_runs_dir, run_folders, sync_runs
    from rig.lab.url import masked

    url = _url(args)
    if not args.runs_dir.is_dir():
        raise UserInputError(f"--runs-dir {args.runs_dir}: no such folder; name the runs folder")
    check_runs_dir(args.runs_dir)
    report = sync_runs(url, run_folders(args.runs_dir))
    for problem in report.skipped:
        print(f"rig: WARNING: run {problem}; skipped", file=sys.stderr)
    for problem in report.unreadable:
        print(f"rig: WARNING: cannot read run {problem}; skipped", file=sys.stderr)
    for problem in report.refused:
        print(f"rig: WARNING: run {problem}; not pushed (in 'rig lab audit')", file=sys.stderr)
    for problem in report.not_stored:
        print(f"rig: WARNING: the index cannot store run {problem}; skipped (in 'rig lab audit')",
              file=sys.stderr)  # fmt: skip
    summary = {"added": len(report.added), "already_indexed": report.present,
               "still_running": len(report.running), "unreadable": len(report.unreadable),
               "refused": len(report.refused), "not_stored": len(report.not_stored),
               "skipped": len(report.skipped)}  # fmt: skip
    refused = len(report.refused) + len(report.not_stored)
    skipped = len(report.skipped)
    _emit(args, summary, f"{len(report.added)} runs added to {masked(url)}"
          f" ({report.present} already there, {len(report.running)} still running"
          + (f", {refused} refused" if refused else "")
          + (f", {skipped} skipped" if skipped else "") + ")")  # fmt: skip
    return 1 if refused or skipped else 0


def _cmd_runs(args: argparse.Namespace) -> int:
    from rig.lab.queries import runs, table

    if args.limit < 1:
        raise UserInputError(f"--limit {args.limit}: give a positive number of runs")
    conn = _query(args)
    try:
        rows = runs(conn, dut=args.dut, status=args.status, limit=args.limit)
    finally:
        conn.close()
    _emit(args, rows, table(rows))
    return 0


def _cmd_dut(args: argparse.Namespace) -> int:
    from rig.lab.queries import dut, table

    conn = _query(args)
    try:
        rows = dut(conn, args.serial)
    finally:
        conn.close()
    cols = ["run_id", "rig", "started_at", "procedure", "status", "verdict", "failed_criteria",
            "min_margin", "operator", "report_files"]  # fmt: skip
    _emit(args, rows, table(rows, cols) if rows else f"no runs of {args.serial} in the index")
    return 0


def _cmd_trend(args: argparse.Namespace) -> int:
    from rig.lab.queries import table, trend

    conn = _query(args)
    try:
        tr = trend(conn, args.param, lot=args.lot)
    finally:
        conn.close()
    if not tr.rows:
        raise UserInputError(
            f"no values of {args.param!r}{f' in lot {args.lot}' if args.lot else ''} in the index;"
            " name a calibration parameter (see 'rig lab trend --help')"
        )
    if args.png is not None:
        from rig.lab.plot import trend_png

        try:
            trend_png(tr, args.png)
        except OSError as exc:
            raise UserInputError(
                f"cannot write {args.png}: {exc.strerror}; choose another path"
            ) from None
    limits = [{"series": name, **lim} for name, lim in sorted(tr.limits.items())]
    cols = ["run_id", "rig", "lot", "source", "dut_serial", "started_at", "value", "sigma",
            "outlier"]  # fmt: skip
    text = (
        f"{table(tr.rows, cols)}\n\n{tr.runs} runs, {len(tr.rows)} calibrations; control limits"
        f" (mean +- 3 sigma of each calibration in each lot):\n{table(limits)}"
    )
    if args.png is not None:
        text += f"\n\nplot: {args.png}"
    _emit(args, {"param": tr.param, "rows": tr.rows, "limits": limits}, text)
    return 0


def _cmd_audit(args: argparse.Namespace) -> int:
    from rig.lab.queries import audit, table

    conn = _query(args)
    try:
        found = audit(conn)
    finally:
        conn.close()
    text = "\n\n".join([
        "runs with an expired instrument certificate:\n" + table(found["expired_certificates"]),
        "runs without a seal (no data hash):\n" + table(found["unsealed"]),
        "runs a sync refused (changed since sealed, or not storable):\n"
        + table(found["refused"], ["run_id", "rig", "kind", "last_at", "attempts", "reason"]),
        "per rig: failed criteria and values outside their lot's control limits:\n"
        + table(found["rigs"]),
    ])  # fmt: skip
    _emit(args, found, text)
    return 0
