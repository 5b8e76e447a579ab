"""``rig run``, ``rig check``, ``rig demo``, ``rig runs``, ``rig show``, ``rig export``."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from rig.config import RigConfig, load_rig_config
from rig.errors import UserInputError
from rig.procedure.language import FIELD_STEPS, Procedure, parse_procedure
from rig.procedure.plan import ABSOLUTE_MAX_FIELD_UT, dry_run, rig_timing

PROCEDURES_DIR = Path(__file__).resolve().parent.parent / "procedures"


def find_procedure(name: str) -> Path:
    """A procedure by path, or by name in the shipped ``procedures/`` folder."""
    p = Path(name)
    if p.exists():
        return p
    shipped = PROCEDURES_DIR / (name if name.endswith(".yaml") else f"{name}.yaml")
    if shipped.exists():
        return shipped
    names = ", ".join(sorted(f.stem for f in PROCEDURES_DIR.glob("*.yaml")))
    raise UserInputError(f"no procedure '{name}': give a path or one of: {names}")


def parse_sets(items: list[str]) -> dict[str, str]:
    """``--set name=value`` pairs."""
    out = {}
    for item in items:
        if "=" not in item:
            raise UserInputError(f"--set {item!r}: write --set name=value")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def cage_model_arrays(cfg: RigConfig | None) -> tuple[Any, Any]:
    """The cage model for a dry run: the calibration file if there is one, else the nominal K."""
    if cfg is None or cfg.cage is None:
        return None, None
    from rig.cage.model import CageModel

    if cfg.cage.calibration is not None and cfg.cage.calibration.exists():
        m = CageModel.load(cfg.cage.calibration)
        return m.k_ut_per_a, m.b0_ut
    if cfg.cage.nominal_k_ut_per_a is not None:
        return np.array(cfg.cage.nominal_k_ut_per_a), np.zeros(3)
    return None, None


def run_check(procedure: str, rig_config: Path | None, sets: list[str], quiet: bool) -> int:
    """Dry run: timeline, duration, peaks against limits. Exit 0 only when every limit was checked
    and holds; 1 on a violation or when limits could not be checked (no ``--rig``, no cage model)."""
    proc = parse_procedure(find_procedure(procedure), parse_sets(sets))
    cfg = load_rig_config(rig_config) if rig_config else None
    k, b0 = cage_model_arrays(cfg)
    loads_max = {}
    unchecked: list[str] = []
    if cfg is not None:
        for name in proc.loads:
            if name not in cfg.devices:
                raise UserInputError(f"{proc.path}: load '{name}' is not a device in {cfg.path}")
            limit = cfg.devices[name].get("max_current_a")
            if limit is not None:
                loads_max[name] = float(limit)
    cage = cfg.cage if cfg is not None else None
    dr = dry_run(
        proc,
        k,
        b0,
        cage.max_current_a if cage else None,
        cage.max_field_ut if cage else None,
        loads_max,
        rig_timing(cfg),
    )
    if cfg is None:
        unchecked.append(
            "no rig configuration given (--rig CONFIG.toml); the rig's field, coil current and"
            f" load current limits were not checked (only |B| <= {ABSOLUTE_MAX_FIELD_UT:g} uT)"
        )
    elif cage is None:
        unchecked.append(
            f"{cfg.path} has no [cage] section; field and coil current limits were not checked"
        )
    elif k is None and any(s.kind in FIELD_STEPS for s in proc.steps):
        unchecked.append(
            f"{cfg.path} has no cage model ([cage].calibration file or nominal_k_ut_per_a); coil"
            " currents were not checked: run cage-characterization or add nominal_k_ut_per_a"
        )
    no_limit = [ch for ch in dr.peak_load_a if ch not in loads_max] if cfg is not None else []
    if not quiet:
        live = any(s.kind == "live_calibrate" for s in proc.steps)
        how_long = "at most" if live else "about"
        print(
            f"{proc.title} ({proc.path}): {len(proc.steps)} steps, {how_long} {dr.duration_s:.0f} s"
            + (" (live_calibrate steps may stop earlier)" if live else "")
        )
        for t, name, summary in dr.timeline:
            print(f"  {t:7.1f} s  {name:<28} {summary}")
        print(
            f"peak |B| {dr.peak_field_ut:.1f} uT"
            + (f" (limit {cage.max_field_ut:g})" if cage else "")
        )
        if k is not None:
            print("peak coil currents " + ", ".join(f"{'xyz'[i]} {a:.3f} A" for i, a in enumerate(dr.peak_current_a))
                  + (f" (limits {', '.join(f'{x:g}' for x in cage.max_current_a)} A)" if cage else ""))  # fmt: skip
        for ch, amps in dr.peak_load_a.items():
            limit_text = f" (limit {loads_max[ch]:g})" if ch in loads_max else ""
            print(f"peak load {ch} {amps:.3f} A{limit_text}")
        if no_limit and cfg is not None:
            print(
                f"note: {', '.join(no_limit)} {'has' if len(no_limit) == 1 else 'have'} no"
                f" max_current_a in {cfg.path}: only the instrument limits the current"
            )
    for v in dr.violations:
        print(f"LIMIT: {v}")
    for u in unchecked:
        print(f"NOT CHECKED: {u}")
    if not quiet:
        if dr.violations:
            print(f"{len(dr.violations)} limit violation(s): fix the procedure")
        elif unchecked:
            print("limits NOT CHECKED (see above): not known to be safe on the rig")
        else:
            print(f"OK: within the limits of {cfg.path if cfg else '?'}")
    return 0 if not dr.violations and not unchecked else 1


def _confirm_all(text: str) -> bool:
    print(f"[auto-confirmed] {text}")
    return True


def _confirm_all_quietly(text: str) -> bool:
    return True  # the run records every prompt and that it was confirmed


def summarize(outcome: Any, quiet: bool) -> None:
    """A short terminal summary of a finished run. With ``quiet`` only a run that did not complete
    says so: one line on stderr with its status and reason (``-q`` means errors only, not nothing)."""
    verdict = outcome.results.get("verdict")
    if quiet:
        if outcome.status != "complete":
            failed = [
                r["name"] for r in (verdict or {}).get("criteria", []) if r["verdict"] != "PASS"
            ]
            what = f" ({', '.join(failed)})" if outcome.status == "failed" and failed else ""
            prefix = "error: " if outcome.status == "error" else ""
            print(
                f"rig: {prefix}run {outcome.folder.name} ended with status {outcome.status}:"
                f" {outcome.reason}{what}; data in {outcome.folder}",
                file=sys.stderr,
            )
        return
    print(f"run {outcome.folder.name}: {outcome.status} ({outcome.reason})")
    if verdict:
        for row in verdict["criteria"]:
            print(f"  {row['verdict']:<4} {row['name']:<28} {_criterion_value(row)}")
        print(f"VERDICT: {verdict['overall']}")
    for name in ("report.html", "report.pdf"):
        if (outcome.folder / name).exists():
            print(f"report: {outcome.folder / name}")
    print(f"data:   {outcome.folder / 'run.sqlite'}")


def run_procedure(
    procedure: str, rig_config: Path, sets: list[str], runs_dir: Path, yes: bool, quiet: bool
) -> int:
    """``rig run``: execute on the rig named by the configuration."""
    from rig.engine.runner import Runner

    proc = parse_procedure(find_procedure(procedure), parse_sets(sets))
    cfg = load_rig_config(rig_config)
    confirm = (_confirm_all_quietly if quiet else _confirm_all) if yes else None
    runner = Runner(proc, cfg, runs_dir, confirm=confirm, quiet=quiet)
    outcome = runner.run()
    summarize(outcome, quiet)
    return outcome.exit_code


def run_demo(runs_dir: Path, procedure: str, quiet: bool) -> int:
    """``rig demo``: start ``rig sim`` as a child process, run a shipped procedure on it without
    prompts, stop the simulator. A separate process gives the simulator its own core, as real
    instruments have their own electronics. The child dies with this process (Linux: the kernel
    sends it SIGTERM; see rig.child_process), so a killed demo leaves no simulator behind."""
    from rig.child_process import start_child, stop_child
    from rig.engine.runner import Runner

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
        confirm = _confirm_all_quietly if quiet else _confirm_all
        outcome = Runner(proc, cfg, runs_dir, confirm=confirm, quiet=quiet).run()
    finally:
        stop_child(child, wait_s=15.0)  # SIGINT, then SIGKILL after 15 s
    summarize(outcome, quiet)
    if not quiet:
        print(f"demo took {time.monotonic() - t0:.0f} s")
    return outcome.exit_code


def _criterion_value(row: dict[str, Any]) -> str:
    """A verdict row's value with its unit and limits, or why it has none."""
    if "value" not in row:
        return str(row.get("reason", ""))
    unit = f" {row['unit']}" if row.get("unit") else ""
    lo, hi = row.get("min"), row.get("max")
    limits = (
        f"{lo:g}..{hi:g}"
        if lo is not None and hi is not None
        else (f"max {hi:g}" if hi is not None else (f"min {lo:g}" if lo is not None else ""))
    )
    return f"{row['value']:.4g}{unit}" + (f"  ({limits})" if limits else "")


def run_verdict(folder: Path) -> str | None:
    """The overall verdict (PASS/FAIL) stored by a run's check step, None without one."""
    from rig.store import RunReader

    reader = RunReader(folder)
    try:
        verdict = reader.results().get("verdict")
    finally:
        reader.close()
    return str(verdict["overall"]) if isinstance(verdict, dict) and "overall" in verdict else None


def list_runs_cmd(runs_dir: Path, quiet: bool) -> int:
    """``rig runs``: one line per run, newest first, with its status and verdict."""
    from rig.store import list_runs

    runs = list_runs(runs_dir)
    if not runs:
        print(f"no runs in {runs_dir}")
        return 0
    width = max(len("RUN"), *(len(r.run_id) for r in runs))
    print(f"{'RUN':<{width}} {'STATUS':<10} {'VERDICT':<7} {'PROCEDURE':<24} DUT")
    for r in runs:
        m = r.meta
        print(
            f"{r.run_id:<{width}} {r.status:<10} {run_verdict(r.folder) or '-':<7}"
            f" {m.get('procedure', ''):<24} {m.get('dut_serial', '') or '-'}"
        )
    return 0


def resolve_run(run: str, runs_dir: Path) -> Path:
    """A run folder by path or id."""
    p = Path(run)
    if (p / "run.sqlite").exists():
        return p
    q = runs_dir / run
    if (q / "run.sqlite").exists():
        return q
    raise UserInputError(f"no run '{run}' (looked at {p} and {q}); list runs with 'rig runs'")


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


def show_run(run: str, runs_dir: Path, as_json: bool = False) -> int:
    """``rig show``: a summary of one run; ``as_json`` prints everything stored as one JSON
    document (meta, samples per device, steps, results) and nothing else."""
    from rig.store import RunReader

    folder = resolve_run(run, runs_dir)
    reader = RunReader(folder)
    try:
        meta, results = reader.meta(), reader.results()
        counts = {
            d: int(meta[f"samples_{d}"])
            if isinstance(meta.get(f"samples_{d}"), int)
            else len(reader.samples(d))
            for d in reader.devices()
        }
        steps = reader.steps()
    finally:
        reader.close()
    if as_json:
        doc = {
            "run_id": meta.get("run_id", folder.name),
            "folder": str(folder),
            "meta": meta,
            "samples": counts,
            "steps": [
                {
                    "index": i,
                    "name": n,
                    "kind": k,
                    "t_start": t0,
                    "t_end": t1,
                    "duration_s": None if t1 is None else t1 - t0,
                }
                for i, n, k, t0, t1 in steps
            ],
            "results": results,
        }
        print(json.dumps(_finite(doc), indent=2, default=str, allow_nan=False))
        return 0
    status = meta.get("status", "incomplete")
    print(f"run        {meta.get('run_id', folder.name)}  ({folder})")
    print(
        f"procedure  {meta.get('procedure', '?')} ({meta.get('procedure_file', '?')}),"
        f" rig software {meta.get('software_version', '?')}"
    )
    print(f"DUT        {meta.get('dut_serial') or '-'}   operator {meta.get('operator') or '-'}")
    print(f"status     {status} ({meta.get('reason', '')})")
    took = _seconds_between(meta.get("start_time"), meta.get("end_time"))
    print(
        f"time       {meta.get('start_time', '?')} to {meta.get('end_time', 'not ended')}"
        + (f" ({took:.0f} s)" if took is not None else "")
    )
    print(f"rig        {meta.get('rig_config', '?')}")
    instruments = meta.get("instruments") or {}
    if instruments:
        print("instruments")
        for name, ident in instruments.items():
            print(f"  {name:<14} {ident}")
    print("samples    " + (", ".join(f"{d} {n}" for d, n in counts.items()) or "none"))
    print("steps")
    for idx, name, kind, t0, t1 in steps:
        took_s = f"{t1 - t0:7.1f} s" if t1 is not None else "not finished"
        print(f"  {idx + 1:2d} {name:<28} {kind:<18} {took_s}")
    others = {k: v for k, v in results.items() if k != "verdict"}
    if others:
        print("results")
        for name, value in others.items():
            print(f"  {name:<28} {_result_summary(value)}")
    verdict = results.get("verdict")
    if isinstance(verdict, dict):
        print("criteria")
        for row in verdict.get("criteria", []):
            print(f"  {row['verdict']:<4} {row['name']:<32} {_criterion_value(row)}")
        print(f"VERDICT: {verdict.get('overall')}")
    else:
        print("VERDICT: - (no check step)")
    print(f"everything stored: rig show {folder} --json")
    return 0


def report_run(run: str, runs_dir: Path, quiet: bool) -> int:
    """``rig report``: (re)build the HTML and PDF report of a run."""
    from rig.report.acceptance import build_report

    html_path, pdf_path = build_report(resolve_run(run, runs_dir))
    if not quiet:
        print(f"wrote {html_path}\nwrote {pdf_path}")
    return 0


def export_run(run: str, runs_dir: Path, fmt: str, out: Path | None) -> int:
    """``rig export``."""
    from rig.store import RunReader
    from rig.store.export import export_csv, export_hdf5

    folder = resolve_run(run, runs_dir)
    reader = RunReader(folder)
    try:
        if fmt == "csv":
            files = export_csv(reader, out or folder / "csv")
            print(f"wrote {len(files)} files to {files[0].parent}")
        else:
            path = export_hdf5(reader, out or folder / "run.h5")
            print(f"wrote {path}")
    finally:
        reader.close()
    return 0
