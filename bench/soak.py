"""Soak: an hour of orbit replay on the simulated cage; memory, file descriptors and threads flat?

Starts ``rig sim`` and ``rig run orbit-replay --set duration_s=...`` as child processes (as on a
bench), samples the rig process every 10 s from /proc (resident memory, open file descriptors,
threads) and prints the first and last five minutes side by side: a ratio near 1 is flat. Not a
CI job (it takes the hour); quote its figures in the closing note.

    .venv/bin/python bench/soak.py [--minutes 60]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def proc_stats(pid: int) -> tuple[float, int, int]:
    """Resident memory (MB), open file descriptors and threads of ``pid``."""
    status = Path(f"/proc/{pid}/status").read_text()
    rss_kb = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:"))
    threads = next(
        int(line.split()[1]) for line in status.splitlines() if line.startswith("Threads:")
    )
    fds = len(os.listdir(f"/proc/{pid}/fd"))
    return rss_kb / 1024.0, fds, threads


def median(values: list[float]) -> float:
    s = sorted(values)
    return s[len(s) // 2] if s else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--every-s", type=float, default=10.0)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="rig-soak-"))
    rig_toml = work / "rig.toml"
    sim = subprocess.Popen(
        [sys.executable, "-m", "rig.cli", "-q", "sim", "--rig-config", str(rig_toml)]
    )
    try:
        while not rig_toml.exists():
            if sim.poll() is not None:
                raise SystemExit("rig sim did not start")
            time.sleep(0.1)
        duration_s = int(args.minutes * 60)
        run = subprocess.Popen([sys.executable, "-m", "rig.cli", "-q", "run", "orbit-replay", "--rig",
                                str(rig_toml), "--yes", "--runs-dir", str(work / "runs"), "--set",
                                f"duration_s={duration_s}"])  # fmt: skip
        rows: list[tuple[float, float, int, int]] = []
        t0 = time.monotonic()
        print(f"soak: {args.minutes:g} min orbit replay, rig pid {run.pid}, data in {work}")
        print(f"{'t (min)':>8} {'RSS (MB)':>9} {'fds':>5} {'threads':>8}")
        while run.poll() is None:
            try:
                rss, fds, threads = proc_stats(run.pid)
            except (FileNotFoundError, ProcessLookupError, StopIteration):
                break
            t_min = (time.monotonic() - t0) / 60.0
            rows.append((t_min, rss, fds, threads))
            if len(rows) % max(1, int(300 / args.every_s)) == 1:
                print(f"{t_min:8.1f} {rss:9.1f} {fds:5d} {threads:8d}", flush=True)
            time.sleep(args.every_s)
        code = run.wait()
    finally:
        sim.send_signal(signal.SIGINT)
        sim.wait(timeout=30)
    window = 5.0
    replay = [r for r in rows if r[0] > 1.0]  # after start-up (imports, cage characterization)
    if not replay:
        print("the run ended before the soak began")
        return 1
    end = replay[-1][0]
    first = [r for r in replay if r[0] <= replay[0][0] + window]
    last = [r for r in replay if r[0] >= end - window]
    print(
        f"\nrig run exit code {code} after {rows[-1][0]:.1f} min; {len(rows)} samples of the process"
    )
    for i, (name, unit) in enumerate((("RSS", "MB"), ("fds", ""), ("threads", "")), start=1):
        a, b = median([r[i] for r in first]), median([r[i] for r in last])
        lo, hi = min(r[i] for r in replay), max(r[i] for r in replay)
        print(f"  {name:8s} first 5 min {a:8.1f} {unit:2s} last 5 min {b:8.1f} {unit:2s}"
              f" ratio {b / a:5.3f}  (range {lo:.1f}-{hi:.1f})")  # fmt: skip
    from rig.store import RunReader

    folder = next((p for p in (work / "runs").iterdir() if (p / "run.sqlite").exists()), None)
    if folder is not None:
        reader = RunReader(folder)
        meta = reader.meta()
        print(f"  run status {meta.get('status')} ({meta.get('reason')}); {reader.count('samples')} samples"
              f" stored; command lateness p99 {meta.get('command_lateness_p99_ms', float('nan')):.2f} ms,"
              f" max {meta.get('command_lateness_max_ms', float('nan')):.1f} ms")  # fmt: skip
        reader.close()
    return 0 if code == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
