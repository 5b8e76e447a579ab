"""The verdict does not depend on how busy the computer is (issue 30): `rig demo` N times on the
idle machine, then N times under mixed load - a second `rig demo` in parallel and CPU hogs on
every core - measured in the same invocation.

Per run it prints the status and verdict, the vector and scalar fit residuals (nT rms), the DUT
samples the timing check left out as misdated and the largest timing error it found (ms), and
the p99 lateness of scheduled commands. The summary compares the loaded runs' residuals with the
idle runs' median (goal: within 1.5x) and counts wrong verdicts (goal 0: the simulated DUT is
good, so every complete run must PASS; a run flagged for a re-run is not a wrong verdict).

Usage: python bench/bench_verdict_under_load.py [--runs 10] [--hogs 2] [--skip-idle]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench_prediction import cage_time_s
from under_load import cpu_hogs

from rig.store import RunReader


def _demo(runs_dir: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "rig.cli", "-q", "demo", "--runs-dir", str(runs_dir)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip


def _figures(runs_dir: Path, exit_code: int, wall_s: float) -> dict[str, Any]:
    """The run's status, verdict, residuals and timing figures."""
    folders = [p for p in runs_dir.iterdir() if (p / "run.sqlite").exists()]
    if not folders:
        return {"status": "no run", "exit": exit_code, "wall_s": wall_s}
    reader = RunReader(max(folders, key=lambda p: p.name))
    try:
        meta, results, steps = reader.meta(), reader.results(), reader.steps()
    finally:
        reader.close()
    out: dict[str, Any] = {"status": meta.get("status"), "reason": meta.get("reason", ""),
                           "exit": exit_code, "wall_s": wall_s, "verdict": "-",
                           "p99_ms": meta.get("command_lateness_p99_ms", float("nan")),
                           "misdated": 0, "timing_ms": 0.0, "failed": [], "targets": 0,
                           "cage_s": cage_time_s(steps)}  # fmt: skip
    for res in results.values():
        if not isinstance(res, dict):
            continue
        if "overall" in res:
            out["verdict"] = res["overall"]
            criteria = res.get("criteria", [])
            out["failed"] = [c["name"] for c in criteria if c.get("verdict") != "PASS"]
            out["targets"] = sum(1 for c in criteria if c["name"].endswith(" 1-sigma"))
        if "residual_rms_nt" in res and res.get("model") in ("vector", "scalar"):
            out[f"{res['model']}_nt"] = float(res["residual_rms_nt"])
            out["misdated"] += int(res.get("misdated_samples", 0))
            out["timing_ms"] = max(out["timing_ms"], 1000.0 * float(res.get("timing_error_s", 0.0)))
    return out


def _row(label: str, f: dict[str, Any]) -> str:
    return (f"  {label:<12} {f.get('status', '?'):<10} {f.get('verdict', '-'):<5}"
            f" vector {f.get('vector_nt', float('nan')):6.1f} nT  scalar"
            f" {f.get('scalar_nt', float('nan')):6.1f} nT  misdated {f.get('misdated', 0):3d}"
            f" (worst {f.get('timing_ms', 0.0):5.0f} ms)  p99 lateness"
            f" {f.get('p99_ms', float('nan')):6.1f} ms  {f['wall_s']:4.0f} s (cage"
            f" {f.get('cage_s', float('nan')):5.1f} s)"
            + (f"  failed: {', '.join(f['failed'])}" if f.get("failed") else ""))  # fmt: skip


def run_phase(tmp: Path, runs: int, parallel: bool) -> list[dict[str, Any]]:
    """``runs`` rounds of one demo (or two at once); the figures of every run."""
    out = []
    for i in range(runs):
        dirs = [tmp / f"{i}-a"] + ([tmp / f"{i}-b"] if parallel else [])
        t0 = time.monotonic()
        procs = [_demo(d) for d in dirs]
        for d, p in zip(dirs, procs, strict=True):
            _, err = p.communicate()
            f = _figures(d, p.returncode, time.monotonic() - t0)
            if f.get("status") not in ("complete", "failed"):
                f["reason"] = f.get("reason") or err.decode(errors="replace").strip()[-200:]
            out.append(f)
            ended = f.get("status") not in ("complete", "failed") and f.get("reason")
            print(_row(f"{i + 1}{d.name[-1]}", f) + (f"  ({f['reason']})" if ended else ""),
                  flush=True)  # fmt: skip
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--runs", type=int, default=10, help="rounds per phase (default 10)")
    ap.add_argument("--hogs", type=int, default=os.cpu_count() or 2, help="CPU hogs under load")
    ap.add_argument("--skip-idle", action="store_true", help="no idle-machine runs")
    ap.add_argument("--skip-record", action="store_true",
                    help="do not write bench/results/demo_time.json")  # fmt: skip
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="verdict-under-load-"))
    idle: list[dict[str, Any]] = []
    if not args.skip_idle:
        print(f"idle: {args.runs} x rig demo; load average {os.getloadavg()[0]:.1f}", flush=True)
        idle = run_phase(tmp / "idle", args.runs, parallel=False)
    with cpu_hogs(args.hogs) as what:
        print(f"loaded: {args.runs} x two rig demo at once beside {what}", flush=True)
        loaded = run_phase(tmp / "loaded", args.runs, parallel=True)
    wrong = [
        f for f in loaded + idle if f.get("status") == "complete" and f.get("verdict") != "PASS"
    ]
    wrong += [f for f in loaded + idle if f.get("status") == "failed"]
    flagged = [f for f in loaded + idle if f.get("status") not in ("complete", "failed")]
    print(f"\n{len(loaded)} loaded runs, {len(idle)} idle runs")
    for model in ("vector", "scalar"):
        lo = [f[f"{model}_nt"] for f in loaded if f"{model}_nt" in f]
        if idle and lo:
            base = statistics.median(f[f"{model}_nt"] for f in idle if f"{model}_nt" in f)
            print(f"  {model} residual: idle median {base:.1f} nT; loaded median"
                  f" {statistics.median(lo):.1f} nT, worst {max(lo):.1f} nT ="
                  f" {max(lo) / base:.2f}x the idle median (goal <= 1.5x)")  # fmt: skip
    print(f"  misdated samples left out under load: {sum(f['misdated'] for f in loaded)}"
          f" (worst timing error {max((f['timing_ms'] for f in loaded), default=0):.0f} ms)")  # fmt: skip
    print(f"  wrong verdicts {len(wrong)}, runs that did not complete {len(flagged)}")
    _targets_and_cage_time(idle + loaded)
    if idle and loaded and not args.skip_record:
        record_demo_time(idle, loaded)
    return 0 if not wrong else 1


def _targets_and_cage_time(runs: list[dict[str, Any]]) -> None:
    """Print how many complete runs met every sigma target (criteria named "... 1-sigma") and the
    cage time the runs took."""
    done = [f for f in runs if f.get("status") in ("complete", "failed") and f.get("targets")]
    if not done:
        return
    missed = [f for f in done if any(n.endswith(" 1-sigma") for n in f["failed"])]
    cage = [f["cage_s"] for f in done]
    print(f"  sigma targets ({done[0]['targets']} each) met in {len(done) - len(missed)} of"
          f" {len(done)} runs; cage time {min(cage):.1f}-{max(cage):.1f} s,"
          f" median {statistics.median(cage):.1f} s")  # fmt: skip


RECORD = Path(__file__).resolve().parent / "results" / "demo_time.json"
"""The demo's wall times as last measured here: the README states them and a test holds the two
together (tests/test_readme.py)."""


def record_demo_time(idle: list[dict[str, Any]], loaded: list[dict[str, Any]]) -> None:
    """Write :data:`RECORD` (s, whole seconds) and print the README line's figures."""

    def span(runs: list[dict[str, Any]]) -> list[int]:
        walls = [round(f["wall_s"]) for f in runs if f.get("status") == "complete"]
        return [min(walls), max(walls)] if walls else []

    record = {"date": time.strftime("%Y-%m-%d"), "idle_s": span(idle), "loaded_s": span(loaded),
              "runs": {"idle": len(idle), "loaded": len(loaded)}}  # fmt: skip
    RECORD.parent.mkdir(exist_ok=True)
    RECORD.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    print(f"  recorded in {RECORD}: update README's demo time to match (a test checks it)")


if __name__ == "__main__":
    sys.exit(main())
