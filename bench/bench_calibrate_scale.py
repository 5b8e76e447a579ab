"""``rig calibrate`` at flight-log scale (issue 19): whole-process time and peak memory.

Prints, in one run, each figure next to its goal and to baselines measured in the same run:
  * 100k samples x 24 parameters (5 telemetry channels): median wall time over --repeat runs of
    the whole ``rig calibrate`` process, against the whole-process scipy baseline
    (``bench/scipy_baseline_fit.py``: the same CSV, the same model, ``least_squares`` with a
    finite-difference Jacobian), goal <= 0.5 s and >= 5x;
  * 1M x 24 (goal <= 4 s, <= 600 MB peak RSS), 100k x 69 (20 channels; goal <= 1.5 s, <= 400 MB),
    10M x 24 (--big; goal <= 1.5 GB, time printed);
  * ``rig --help`` against ``python -c pass`` (goal <= 0.15 s) and the modules the two commands
    import (``python -X importtime``): neither may import matplotlib, h5py,
    scipy, the drivers, the store, the filters or the rest of FORBIDDEN.

Peak RSS is each child's own (``os.wait4``). The machine is shared: medians, and ratios against
baselines run alongside, are the figures to read; no figure here is asserted in a test.

Usage: python bench/bench_calibrate_scale.py [--repeat R] [--big] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rig.calibration.synthetic import rax_like

HERE = Path(__file__).resolve().parent
PIECE = 500_000
FORBIDDEN = ("matplotlib", "h5py", "scipy", "serial", "pymodbus", "smbus2", "sgp4", "ppigrf",
             "filterpy", "yaml", "sqlite3", "sim", "rig.store", "rig.engine",
             "rig.calibration.sequential", "rig.calibration.profiled")  # fmt: skip
"""Modules neither command needs (the drivers' error classes, ``drivers.errors``, are allowed:
the CLI maps them to exit codes)."""


def write_csv(path: Path, n: int, channels: int) -> list[str]:
    """A RAX-like tumbling-CubeSat log (field magnitude reference), written in pieces."""
    names: list[str] = []
    with path.open("w", encoding="utf-8") as fh:
        for start in range(0, n, PIECE):
            case = rax_like(min(PIECE, n - start), seed=5, channels=channels, start_s=float(start))
            s = case.samples
            if not names:
                names = list(s.channels)
                fh.write(",".join(["mx", "my", "mz", "b", *names]) + "\n")
            data = np.column_stack([s.measured_ut, s.field_magnitude_ut, s.telemetry])
            np.savetxt(fh, data, delimiter=",", fmt="%.6f")
    return names


def run(cmd: list[str]) -> tuple[float, float]:
    """Wall time (s) and the child's own peak RSS (MB) of one process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}")
    return wall, usage.ru_maxrss / 1024.0


def median_of(repeat: int, cmd: list[str]) -> tuple[float, float]:
    runs = [run(cmd) for _ in range(repeat)]
    return statistics.median(w for w, _ in runs), max(r for _, r in runs)


def calibrate_cmd(csv: Path, names: list[str], out: Path) -> list[str]:
    return [sys.executable, "-m", "rig.cli", "-q", "calibrate", str(csv), "--measured", "mx,my,mz",
            "--field-magnitude", "b", "--telemetry", ",".join(names), "--out", str(out)]  # fmt: skip


def imported(cmd: list[str]) -> set[str]:
    """Top-level packages a process imports (from ``-X importtime``)."""
    err = subprocess.run([cmd[0], "-X", "importtime", *cmd[1:]], capture_output=True, text=True,
                         check=True).stderr  # fmt: skip
    mods = set()
    for line in err.splitlines():
        if line.startswith("import time:") and "|" in line:
            name = line.rsplit("|", 1)[1].strip()
            mods.add(name)
            mods.add(name.split(".")[0])
    return mods


def verdict(ok: bool) -> str:
    return "met" if ok else "MISSED"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--big", action="store_true", help="also 10M samples (a 0.8 GB CSV)")
    ap.add_argument("--keep", type=Path, help="write the CSV files here and keep them")
    args = ap.parse_args()
    tmp = tempfile.TemporaryDirectory()
    folder = args.keep or Path(tmp.name)
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / "result.json"
    ok = True

    def data(n: int, channels: int) -> tuple[Path, list[str]]:
        path = folder / f"rax_{n}_{channels}ch.csv"
        names_file = path.with_suffix(".names")
        if not path.exists() or not names_file.exists():
            names_file.write_text(",".join(write_csv(path, n, channels)))
        return path, names_file.read_text().split(",")

    print(f"python {sys.version.split()[0]}, numpy {np.__version__}, {os.cpu_count()} CPUs;"
          f" medians of {args.repeat} runs")  # fmt: skip

    csv, names = data(100_000, 5)
    cmd = calibrate_cmd(csv, names, out)
    t_ours, rss = median_of(args.repeat, cmd)
    base_cmd = [sys.executable, str(HERE / "scipy_baseline_fit.py"), str(csv), "--measured",
                "mx,my,mz", "--field-magnitude", "b", "--telemetry", ",".join(names)]  # fmt: skip
    t_base, rss_base = median_of(args.repeat, base_cmd)
    good = t_ours <= 0.5 and t_base / t_ours >= 5.0
    ok &= good
    print(f"100k x 24: rig calibrate {t_ours:.3f} s wall, {rss:.0f} MB peak (goal <= 0.5 s);"
          f" scipy whole-process baseline {t_base:.3f} s, {rss_base:.0f} MB: {t_base / t_ours:.1f}x"
          f" (goal >= 5x): {verdict(good)}")  # fmt: skip

    for n, channels, goal_s, goal_mb in ((1_000_000, 5, 4.0, 600.0), (100_000, 20, 1.5, 400.0)):
        csv, names = data(n, channels)
        t, rss = median_of(args.repeat, calibrate_cmd(csv, names, out))
        good = t <= goal_s and rss <= goal_mb
        ok &= good
        print(f"{n // 1000}k x {9 + 3 * channels}: {t:.3f} s wall (goal <= {goal_s:g} s),"
              f" {rss:.0f} MB peak (goal <= {goal_mb:.0f} MB): {verdict(good)}")  # fmt: skip

    if args.big:
        csv, names = data(10_000_000, 5)
        t, rss = run(calibrate_cmd(csv, names, out))
        good = rss <= 1536.0
        ok &= good
        print(f"10M x 24: {t:.1f} s wall (one run), {rss:.0f} MB peak (goal <= 1536 MB):"
              f" {verdict(good)}")  # fmt: skip

    help_cmd = [sys.executable, "-m", "rig.cli", "--help"]
    t_help, _ = median_of(max(args.repeat, 10), help_cmd)
    t_pass, _ = median_of(max(args.repeat, 10), [sys.executable, "-c", "pass"])
    good = t_help <= 0.15
    ok &= good
    print(f"rig --help: {t_help:.3f} s (goal <= 0.15 s); python -c pass {t_pass:.3f} s:"
          f" {verdict(good)}")  # fmt: skip
    csv, names = data(100_000, 5)
    for what, cmd in (("rig --help", help_cmd), ("rig calibrate", calibrate_cmd(csv, names, out))):
        mods = imported(cmd)
        heavy = sorted(m for m in FORBIDDEN if m in mods)
        heavy += sorted(m for m in mods if m.startswith("drivers.") and m != "drivers.errors")
        ok &= not heavy
        print(f"{what} imports {', '.join(heavy) if heavy else 'none of ' + ', '.join(FORBIDDEN)}")
    print("PASS" if ok else "MISS")
    tmp.cleanup()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
