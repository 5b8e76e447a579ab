"""A shipped procedure dry-run in simulated time (``rig demo --simulated-time``), timed with the
simulation's threads on one CPU (the default, :mod:`timebase.one_cpu`) against the same run with
them left where the kernel puts them (``TIMEBASE_CPU=any``, the baseline): wall time, CPU time,
the ratio, and the verdict of each (the same: simulated time does not depend on the computer).

By default the thermal-hysteresis procedure for one hour of its cycle (``--hold-s 3600``; the
shipped procedure holds 14400 s: ``--hold-s 14400`` is the issue's 4-hour dry run).

Usage: ``.venv/bin/python bench/bench_dry_run.py [--procedure NAME] [--hold-s S] [--repeat N]``
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def dry_run(procedure: str, hold_s: float | None, cpu: str | None) -> tuple[float, float, str]:
    """One ``rig demo --simulated-time`` in a fresh folder: (wall s, CPU s, verdict)."""
    env = dict(os.environ)
    env.pop("TIMEBASE_CPU", None)
    if cpu is not None:
        env["TIMEBASE_CPU"] = cpu
    with tempfile.TemporaryDirectory() as folder:
        args = [sys.executable, "-m", "rig.cli", "demo", "--simulated-time", "-q",
                "--procedure", procedure, "--runs-dir", folder]  # fmt: skip
        if hold_s is not None:
            args += ["--set", f"hold_s={hold_s:g}"]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        started = time.perf_counter()
        done = subprocess.run(args, env=env, capture_output=True, text=True, check=False)
        wall = time.perf_counter() - started
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        reports = sorted(Path(folder).glob("*/report.txt"))
        text = reports[0].read_text() if reports else ""
        found = re.search(r"VERDICT: (\w+)", text)
        verdict = found.group(1) if found else f"none (exit {done.returncode})"
    return wall, cpu_s, verdict


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--procedure", default="dut-thermal-hysteresis",
                        help="a shipped procedure's name or a file (default: %(default)s)")  # fmt: skip
    parser.add_argument("--hold-s", type=float, default=3600.0,
                        help="its hold_s parameter (s; 0: the procedure's own, default 3600)")  # fmt: skip
    parser.add_argument("--repeat", type=int, default=1, help="runs of each kind (default 1)")
    args = parser.parse_args()
    hold = args.hold_s or None
    rows: dict[str, list[tuple[float, float, str]]] = {"one CPU": [], "any CPU (baseline)": []}
    for _ in range(args.repeat):
        for label, cpu in (("one CPU", None), ("any CPU (baseline)", "any")):
            rows[label].append(dry_run(args.procedure, hold, cpu))
    print(f"{args.procedure}, hold_s {hold or 'as shipped'}, {args.repeat} run(s) each:")
    medians = {}
    for label, runs in rows.items():
        medians[label] = statistics.median(w for w, _, _ in runs)
        cpu_s = statistics.median(c for _, c, _ in runs)
        verdicts = ", ".join(sorted({v for _, _, v in runs}))
        print(f"  {label:<20} wall {medians[label]:7.1f} s  CPU {cpu_s:7.1f} s  verdict {verdicts}")
    ratio = medians["one CPU"] / medians["any CPU (baseline)"]
    print(f"  ratio one CPU / baseline: {ratio:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
