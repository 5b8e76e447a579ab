"""``rig run``, ``rig check``, ``rig demo``, ``rig runs``, ``rig show``, ``rig export``."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from rig.config import RigConfig, load_rig_config
from rig.errors import UserInputError
from rig.procedure.language import Procedure, parse_procedure
from rig.procedure.plan import dry_run

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
    """Dry run: timeline, duration, peaks against limits. Exit 0 when within limits, 1 otherwise."""
    proc = parse_procedure(find_procedure(procedure), parse_sets(sets))
    cfg = load_rig_config(rig_config) if rig_config else None
    k, b0 = cage_model_arrays(cfg)
    loads_max = {}
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
    )
    if not quiet:
        live = any(s.kind == "live_calibrate" for s in proc.steps)
        how_long = "at most" if live else "about"
        print(
            f"{proc.title} ({proc.path}): {len(proc.steps)} steps, {how_long} {dr.duration_s:.0f} s of field time"
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
        elif cfg is None:
            print("coil currents not checked: give --rig CONFIG")
        for ch, amps in dr.peak_load_a.items():
            print(f"peak load {ch} {amps:.3f} A")
    for v in dr.violations:
        print(f"LIMIT: {v}")
    if not quiet:
        print(
            "OK: within limits"
            if not dr.violations
            else f"{len(dr.violations)} limit violation(s): fix the procedure"
        )
    return 0 if not dr.violations else 1


def _confirm_all(text: str) -> bool:
    print(f"[auto-confirmed] {text}")
    return True


def summarize(outcome: Any, quiet: bool) -> None:
    """A short terminal summary of a finished run."""
    if quiet:
        return
    print(f"run {outcome.folder.name}: {outcome.status} ({outcome.reason})")
    verdict = outcome.results.get("verdict")
    if verdict:
        for row in verdict["criteria"]:
            value = f"{row['value']:.4g}" if "value" in row else row.get("reason", "")
            print(f"  {row['verdict']:<4} {row['name']:<28} {value}")
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
    runner = Runner(proc, cfg, runs_dir, confirm=_confirm_all if yes else None, quiet=quiet)
    outcome = runner.run()
    summarize(outcome, quiet)
    return outcome.exit_code


def run_demo(runs_dir: Path, procedure: str, quiet: bool) -> int:
    """``rig demo``: start ``rig sim`` as a child process, run a shipped procedure on it without
    prompts, stop the simulator. A separate process gives the simulator its own core, as real
    instruments have their own electronics."""
    import signal
    import subprocess
    import sys

    from rig.engine.runner import Runner

    t0 = time.monotonic()
    proc: Procedure = parse_procedure(find_procedure(procedure))
    runs_dir.mkdir(parents=True, exist_ok=True)
    rig_toml = runs_dir / "sim-rig.toml"
    rig_toml.unlink(missing_ok=True)
    child = subprocess.Popen(
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
        outcome = Runner(proc, cfg, runs_dir, confirm=_confirm_all, quiet=quiet).run()
    finally:
        child.send_signal(signal.SIGINT)
        try:
            child.wait(timeout=15)
        except subprocess.TimeoutExpired:
            child.kill()
    summarize(outcome, quiet)
    if not quiet:
        print(f"demo took {time.monotonic() - t0:.0f} s")
    return outcome.exit_code


def list_runs_cmd(runs_dir: Path, quiet: bool) -> int:
    """``rig runs``."""
    from rig.store import list_runs

    runs = list_runs(runs_dir)
    if not runs:
        print(f"no runs in {runs_dir}")
        return 0
    for r in runs:
        m = r.meta
        print(
            f"{r.run_id:<36} {r.status:<10} {m.get('procedure', ''):<24} DUT {m.get('dut_serial', '')}"
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


def show_run(run: str, runs_dir: Path) -> int:
    """``rig show``."""
    from rig.store import RunReader

    reader = RunReader(resolve_run(run, runs_dir))
    try:
        meta, results = reader.meta(), reader.results()
        print(
            json.dumps(
                {k: meta[k] for k in sorted(meta) if k not in ("cage_model",)},
                indent=2,
                default=str,
            )
        )
        print("samples: " + ", ".join(f"{d} {len(reader.samples(d))}" for d in reader.devices()))
        for idx, name, kind, t0, t1 in reader.steps():
            print(
                f"  step {idx + 1:2d} {name:<28} {kind:<18} {('%.1f s' % (t1 - t0)) if t1 else 'not finished'}"
            )
        if "verdict" in results:
            print(f"verdict: {results['verdict']['overall']}")
    finally:
        reader.close()
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
