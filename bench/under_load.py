"""The rig on a busy computer: `rig demo` and a 120 s 50 Hz orbit replay while CPU hogs keep every
core busy, against the same runs on the idle machine measured in the same invocation.

Both run as a technician runs them: `rig run` / `rig demo` subprocesses, the simulated cage in its
own process. Per run it prints the exit status (an abort is any run that did not complete), the
magnetometer samples received against those expected from the sensor rate and the gaps longer
than 1.5 sample periods, and the lateness of scheduled commands (p50, p99, max). Goal under load:
0 aborts, 0 gaps. The hog is `stress-ng --cpu N` when installed, else N Python busy loops.

Usage: python bench/under_load.py [--seconds 120] [--hogs 2] [--skip-baseline] [--skip-demo]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from bench_orbit_replay import PROCEDURE, sample_gaps

from rig.store import RunReader


def _spin() -> None:
    while True:
        pass


@contextmanager
def cpu_hogs(n: int) -> Iterator[str]:
    """``n`` processes that keep a core busy each, for the duration of the block."""
    if n <= 0:
        yield "idle"
        return
    if shutil.which("stress-ng"):
        proc = subprocess.Popen(["stress-ng", "--cpu", str(n), "--cpu-method", "matrixprod",
                                 "--timeout", "3600s"], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)  # fmt: skip
        try:
            yield f"stress-ng --cpu {n}"
        finally:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=20)
        return
    procs = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(n)]
    for p in procs:
        p.start()
    try:
        yield f"{n} Python busy loops"
    finally:
        for p in procs:
            p.kill()


def _stats(folder: Path, exit_code: int, wall_s: float, whole_run: bool) -> dict[str, Any]:
    reader = RunReader(folder)
    try:
        meta = reader.meta()
        gaps = sample_gaps(reader, whole_run=whole_run)
    finally:
        reader.close()
    return {"status": meta.get("status"), "reason": meta.get("reason", ""), "exit": exit_code,
            "wall_s": wall_s, "p50_ms": meta.get("command_lateness_p50_ms", float("nan")),
            "p99_ms": meta.get("command_lateness_p99_ms", float("nan")),
            "max_ms": meta.get("command_lateness_max_ms", float("nan")), "gaps": gaps}  # fmt: skip


def _newest_run(runs: Path) -> Path:
    return max((p for p in runs.iterdir() if (p / "run.sqlite").exists()), key=lambda p: p.name)


def orbit_run(tmp: Path, seconds: float) -> dict[str, Any]:
    """`rig sim` + `rig run` of a 50 Hz orbit replay; the run's figures."""
    rig_toml = tmp / "rig.toml"
    sim = subprocess.Popen(
        [sys.executable, "-m", "rig.cli", "-q", "sim", "--rig-config", str(rig_toml)]
    )
    try:
        deadline = time.monotonic() + 60
        while not rig_toml.exists():
            if sim.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("rig sim did not start")
            time.sleep(0.05)
        (tmp / "orbit.yaml").write_text(PROCEDURE.format(seconds=seconds))
        t0 = time.monotonic()
        rc = subprocess.run([sys.executable, "-m", "rig.cli", "-q", "run", str(tmp / "orbit.yaml"),
                             "--rig", str(rig_toml), "--yes", "--runs-dir", str(tmp / "runs")]).returncode  # fmt: skip
        wall = time.monotonic() - t0
    finally:
        sim.send_signal(signal.SIGINT)
        sim.wait(timeout=30)
    return _stats(_newest_run(tmp / "runs"), rc, wall, whole_run=False)


def demo_run(tmp: Path) -> dict[str, Any]:
    """`rig demo` (the README's main command); the run's figures over the whole run."""
    t0 = time.monotonic()
    rc = subprocess.run([sys.executable, "-m", "rig.cli", "-q", "demo", "--runs-dir", str(tmp / "demo")]).returncode  # fmt: skip
    return _stats(_newest_run(tmp / "demo"), rc, time.monotonic() - t0, whole_run=True)


def _print(label: str, s: dict[str, Any]) -> tuple[int, int]:
    aborted = int(s["status"] not in ("complete", "failed"))
    gaps = sum(g[3] for g in s["gaps"].values())
    print(f"  {label:<22} {s['status']} (exit {s['exit']}, {s['wall_s']:.0f} s wall)"
          + (f": {s['reason']}" if aborted else ""))  # fmt: skip
    print(f"  {'':<22} command lateness p50 {s['p50_ms']:.2f} ms, p99 {s['p99_ms']:.2f} ms,"
          f" max {s['max_ms']:.1f} ms")  # fmt: skip
    for dev, (n, expected, rate, g) in s["gaps"].items():
        print(f"  {'':<22} {dev}: {n} samples ({expected:.0f} expected at {rate:.1f} Hz), {g} gaps")
    return aborted, gaps


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seconds", type=float, default=120.0, help="orbit replay length (s)")
    ap.add_argument(
        "--hogs", type=int, default=os.cpu_count() or 2, help="CPU hogs (default: one per core)"
    )
    ap.add_argument("--skip-baseline", action="store_true", help="no idle-machine runs")
    ap.add_argument("--skip-demo", action="store_true", help="orbit replay only")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="under-load-"))
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for phase, hogs in (("idle", 0), ("loaded", args.hogs)):
        if phase == "idle" and args.skip_baseline:
            continue
        with cpu_hogs(hogs) as what:
            print(f"{phase}: {what}; load average {os.getloadavg()[0]:.1f}", flush=True)
            results[phase] = {"orbit": orbit_run(tmp / phase / "orbit", args.seconds)}
            if not args.skip_demo:
                results[phase]["demo"] = demo_run(tmp / phase)
            print(f"  load average at the end {os.getloadavg()[0]:.1f}")
    total_aborts = total_gaps = 0
    for phase, runs in results.items():
        print(f"{phase}:")
        for name, s in runs.items():
            a, g = _print(f"{name}", s)
            if phase == "loaded":
                total_aborts, total_gaps = total_aborts + a, total_gaps + g
    if "idle" in results:
        for name in results["loaded"]:
            idle, loaded = results["idle"][name], results["loaded"][name]
            print(f"{name}: p99 lateness loaded/idle {loaded['p99_ms']:.2f}/{idle['p99_ms']:.2f} ms ="
                  f" {loaded['p99_ms'] / max(idle['p99_ms'], 1e-9):.2f}x; wall {loaded['wall_s'] / idle['wall_s']:.2f}x")  # fmt: skip
    print(f"under load: {total_aborts} aborts, {total_gaps} gaps (goal 0 and 0)")
    print("PASS" if total_aborts == 0 and total_gaps == 0 else "MISS")
    return 0 if total_aborts == 0 and total_gaps == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
