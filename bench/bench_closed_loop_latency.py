"""The closed loop's latency at 50 Hz on the simulated cage in real time (issue 56's must-show):
the shipped closed-loop procedure with a 50 Hz tick and a 50 Hz control law, the DUT sampling at
the tick rate (``--dut-hz``; the built-in cage's HMR2300 streams 20 Hz, so a 50 Hz loop would
wait up to 50 ms for a new reading), run as a technician runs it (``rig demo --procedure
--sim-config``: the simulated cage in its own process, the wall clock), first on the idle machine
(the baseline), then beside CPU hogs, in the same invocation.

Per run it prints the latency from the newest DUT reading behind a new dipole to the cage command
that carries it (p50, p99, max, from the step's per-tick record), the ticks sent more than a period
late, and the run's status; then the loaded p99 against the idle one (a ratio) and the targets
(p99 at most 20 ms idle, 40 ms beside two hogs).

Usage: ``.venv/bin/python bench/bench_closed_loop_latency.py [--seconds 30] [--dut-hz 50] [--hogs 2]``
(needs the ``[hil]`` extra: Basilisk)
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench_closed_loop_3u import shipped_loop
from under_load import cpu_hogs

from rig.store import RunReader
from sim.config import DEFAULT_CONFIG

TARGET_P99_MS = {"idle": 20.0, "loaded": 40.0}


def procedure(seconds: float, rate_hz: float) -> str:
    """The shipped closed-loop procedure at ``rate_hz`` ticks and control, for ``seconds``, no
    early stop (every tick counts) and no check (the latency is the figure)."""
    return shipped_loop({"duration_s": seconds, "rate_hz": rate_hz, "control_hz": rate_hz,
                         "until_deg_s": 0})  # fmt: skip


def cage_config(dut_hz: float) -> str:
    """The built-in simulated cage with the DUT streaming at ``dut_hz``."""
    text = DEFAULT_CONFIG.read_text()
    at = text.index('name = "dut"')
    rate = re.compile(r"rate_hz = \S+").search(text, at)
    assert rate is not None
    return text[: rate.start()] + f"rate_hz = {dut_hz:g}" + text[rate.end() :]


def one_run(tmp: Path, label: str, seconds: float, rate_hz: float,
            dut_hz: float) -> dict[str, Any]:  # fmt: skip
    """One ``rig demo`` of the loop; its latency figures from the run store."""
    path = tmp / f"loop-{label}.yaml"
    path.write_text(procedure(seconds, rate_hz))
    cage = tmp / "cage.toml"
    cage.write_text(cage_config(dut_hz))
    runs = tmp / f"runs-{label}"
    started = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "rig.cli", "-q", "demo", "--procedure", str(path),
                           "--sim-config", str(cage), "--runs-dir", str(runs)],
                          capture_output=True, text=True)  # fmt: skip
    wall = time.perf_counter() - started
    folder = next(p for p in runs.iterdir() if (p / "run.sqlite").exists())
    reader = RunReader(folder)
    try:
        result = reader.results().get("detumble", {})
        status = reader.meta().get("status")
    finally:
        reader.close()
    latency = result.get("latency_ms") or {}
    return {"label": label, "exit": proc.returncode, "status": status, "wall_s": wall,
            "ticks": result.get("ticks"), "late": result.get("late_ticks"),
            "p50": latency.get("p50", float("nan")), "p99": latency.get("p99", float("nan")),
            "max": latency.get("max", float("nan")), "err": proc.stderr.strip()[-300:]}  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="loop length per run (s)")
    parser.add_argument("--rate-hz", type=float, default=50.0, help="ticks and control per s")
    parser.add_argument("--dut-hz", type=float, default=50.0, help="the DUT's sample rate")
    parser.add_argument("--hogs", type=int, default=2, help="CPU hogs beside the loaded run")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        rows.append(one_run(Path(tmp), "idle", args.seconds, args.rate_hz, args.dut_hz))
        with cpu_hogs(args.hogs) as what:
            rows.append(one_run(Path(tmp), "loaded", args.seconds, args.rate_hz, args.dut_hz))
    print(f"closed loop at {args.rate_hz:g} Hz for {args.seconds:g} s, DUT at {args.dut_hz:g} Hz,"
          f" real time; loaded: {what}")  # fmt: skip
    print(f"{'run':<7} {'status':<9} {'ticks':>6} {'late':>5} {'p50 ms':>7} {'p99 ms':>7}"
          f" {'max ms':>7} {'target':>7}")  # fmt: skip
    for r in rows:
        print(f"{r['label']:<7} {r['status']!s:<9} {r['ticks']!s:>6} {r['late']!s:>5}"
              f" {r['p50']:7.1f} {r['p99']:7.1f} {r['max']:7.1f} {TARGET_P99_MS[r['label']]:7.0f}")  # fmt: skip
        if r["exit"] != 0:
            print(f"  exit {r['exit']}: {r['err']}")
    idle, loaded = rows
    print(f"loaded p99 / idle p99: {loaded['p99'] / idle['p99']:.2f}")
    met = all(r["p99"] <= TARGET_P99_MS[r["label"]] and r["exit"] == 0 for r in rows)
    print("targets met" if met else "targets NOT met")
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
