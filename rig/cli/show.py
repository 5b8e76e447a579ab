"""``rig show``: a summary of one run, or everything stored as one JSON document."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rig.cli.common import Parser, Subparsers, add_run, add_runs_dir, criterion_value, resolve_run

if TYPE_CHECKING:
    from rig.verdict import CheckVerdict


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    show = sub.add_parser("show", parents=parents, help="summarize one run (--json: all of it)")
    add_run(show)
    add_runs_dir(show)
    show.add_argument(
        "--json",
        action="store_true",
        help="print everything stored (meta, samples, steps, results) as one JSON document",
    )
    show.set_defaults(func=_cmd_show)


def _cmd_show(args: argparse.Namespace) -> int:
    return show_run(args.run, args.runs_dir, args.json)


def _finite(value: Any) -> Any:
    """JSON without NaN or Infinity (not JSON): non-finite numbers become null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def _seconds_between(start: Any, end: Any) -> float | None:
    import datetime as dt

    try:
        return (dt.datetime.fromisoformat(end) - dt.datetime.fromisoformat(start)).total_seconds()
    except (TypeError, ValueError):
        return None


def _result_summary(value: Any) -> str:
    """The scalar figures at the top of a result (numbers with their unit-named keys, a model or a
    method), then the chi-square verdict when there is one."""
    if not isinstance(value, dict):
        return str(value)
    parts = []
    for key, v in value.items():
        if isinstance(v, bool) or key in ("history_file",):
            continue
        if isinstance(v, int | float):
            parts.append(f"{key} {v:.4g}")
        elif isinstance(v, str) and key in ("model", "method"):
            parts.append(f"{key} {v}")
    chi2 = value.get("chi2")
    if isinstance(chi2, dict) and "verdict" in chi2:
        parts.append(f"chi2 {chi2['verdict']}")
    live = value.get("live")
    if isinstance(live, dict) and "stopped" in live:
        parts.append(f"stopped: {live['stopped']}")
    return ", ".join(parts[:8]) + (", ..." if len(parts) > 8 else "") if parts else "(see --json)"


def verdict_line(status: str, verdict: CheckVerdict | None) -> str:
    """The last line of ``rig show``: the verdict, or why there is none yet or none at all."""
    if verdict is not None:
        return f"VERDICT: {verdict.overall}"
    if status == "running":
        return "VERDICT: not yet judged (running)"
    if status in ("aborted", "failed", "error", "incomplete", "damaged"):
        return f"VERDICT: not judged ({status})"
    return "VERDICT: - (no check step)"


def _read(folder: Path) -> tuple[dict[str, Any], dict[str, Any], dict[str, int], list[Any]]:
    """(meta, results, sample count per device, steps) of a run folder."""
    from rig.store import RunReader

    reader = RunReader(folder)
    try:
        meta, results = reader.meta(), reader.results()
        counts = {
            d: int(meta[f"samples_{d}"])
            if isinstance(meta.get(f"samples_{d}"), int)
            else len(reader.samples(d))
            for d in reader.devices()
        }
        return meta, results, counts, reader.steps()
    finally:
        reader.close()


def _json(folder: Path, meta: dict[str, Any], results: dict[str, Any], counts: dict[str, int],
          steps: list[Any]) -> str:  # fmt: skip
    """Everything stored as one JSON document (no NaN or Infinity)."""
    doc = {
        "run_id": meta.get("run_id", folder.name),
        "folder": str(folder),
        "meta": meta,
        "samples": counts,
        "steps": [{"index": i, "name": n, "kind": k, "t_start": t0, "t_end": t1,
                   "duration_s": None if t1 is None else t1 - t0} for i, n, k, t0, t1 in steps],
        "results": results,
    }  # fmt: skip
    return json.dumps(_finite(doc), indent=2, default=str, allow_nan=False)


def _print_header(folder: Path, meta: dict[str, Any], counts: dict[str, int]) -> None:
    print(f"run        {meta.get('run_id', folder.name)}  ({folder})")
    print(f"procedure  {meta.get('procedure', '?')} ({meta.get('procedure_file', '?')}),"
          f" rig software {meta.get('software_version', '?')}")  # fmt: skip
    print(f"DUT        {meta.get('dut_serial') or '-'}   operator {meta.get('operator') or '-'}")
    print(f"status     {meta.get('status', 'incomplete')} ({meta.get('reason', '')})")
    took = _seconds_between(meta.get("start_time"), meta.get("end_time"))
    print(f"time       {meta.get('start_time', '?')} to {meta.get('end_time', 'not ended')}"
          + (f" ({took:.0f} s)" if took is not None else ""))  # fmt: skip
    print(f"rig        {meta.get('rig_config', '?')}")
    instruments = meta.get("instruments") or {}
    if instruments:
        print("instruments")
        for name, ident in instruments.items():
            print(f"  {name:<14} {ident}")
    print("samples    " + (", ".join(f"{d} {n}" for d, n in counts.items()) or "none"))


def _print_results(steps: list[Any], results: dict[str, Any]) -> None:
    from rig.verdict import VERDICT_RESULT, check_verdict

    print("steps")
    for idx, name, kind, t0, t1 in steps:
        took_s = f"{t1 - t0:7.1f} s" if t1 is not None else "not finished"
        print(f"  {idx + 1:2d} {name:<28} {kind:<18} {took_s}")
    others = {k: v for k, v in results.items() if k != VERDICT_RESULT}
    if others:
        print("results")
        for name, value in others.items():
            print(f"  {name:<28} {_result_summary(value)}")
    verdict = check_verdict(results)
    if verdict is not None:
        print("criteria")
        for row in verdict.criteria:
            print(f"  {row.verdict:<4} {row.name:<32} {criterion_value(row)}")


def show_run(run: str, runs_dir: Path, as_json: bool = False) -> int:
    """``rig show``: a summary of one run; ``as_json`` prints everything stored as one JSON
    document (meta, samples per device, steps, results) and nothing else."""
    from rig.verdict import check_verdict

    folder = resolve_run(run, runs_dir)
    meta, results, counts, steps = _read(folder)
    if as_json:
        print(_json(folder, meta, results, counts, steps))
        return 0
    _print_header(folder, meta, counts)
    _print_results(steps, results)
    print(verdict_line(str(meta.get("status", "incomplete")), check_verdict(results)))
    print(f"everything stored: rig show {folder} --json")
    return 0
