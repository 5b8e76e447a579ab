"""Scalar maximum-likelihood fit: 100 000 samples, 5 telemetry channels (24 parameters).

Prints, in one run:
  * our ML fit (analytic Jacobian, normal-equation Levenberg-Marquardt) against
    ``scipy.optimize.least_squares`` with a finite-difference Jacobian on the same data, the same
    weights and the same starting point (target: at least 10x faster), and that both reach the same
    cost;
  * peak traced memory of our fit;
  * the whole ``rig calibrate`` command on a CSV of the same data, as a subprocess, wall time and
    peak RSS (target: under 1 s).

Usage: python bench/bench_scalar_fit.py [--samples N] [--repeat R]
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from rig.calibration.batch.nonlinear import ml_fit, scalar_start
from rig.calibration.residuals import scalar_noise_gain, scalar_residuals, scalar_residuals_only
from rig.calibration.synthetic import rax_like
from rig.io.csv_table import write_columns


def best_of(repeat: int, fn):  # type: ignore[no-untyped-def]
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    case = rax_like(args.samples, seed=5)
    s = case.samples
    print(
        f"data: {s.n} samples, {s.n_channels} telemetry channels, {9 + 3 * s.n_channels} parameters"
    )
    start = scalar_start(s).p

    t_ours, est = best_of(args.repeat, lambda: ml_fit(s, start=start))
    tracemalloc.start()
    ml_fit(s, start=start)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()

    sw = 1.0 / scalar_noise_gain(start, s)

    def residual(x: np.ndarray) -> np.ndarray:
        return scalar_residuals_only(x, s) * sw

    t_base, base = best_of(
        max(1, args.repeat - 1),
        lambda: least_squares(residual, start, jac="2-point", method="trf", x_scale="jac"),
    )
    r_ours = scalar_residuals(est.p, s)[0] * sw
    cost_ours, cost_base = float(r_ours @ r_ours), float(base.fun @ base.fun)
    max_diff = float(np.max(np.abs(est.p - base.x) / np.sqrt(np.diag(est.covariance))))
    ratio = t_base / t_ours
    print(f"ours   (analytic J, LM normal eqs): {t_ours * 1000:8.1f} ms  cost {cost_ours:.6e}")
    print(
        f"scipy least_squares, 2-point FD J : {t_base * 1000:8.1f} ms  cost {cost_base:.6e}"
        f"  ({base.nfev} evaluations)"
    )
    print(
        f"speed-up: {ratio:.1f}x (target >= 10x)   largest parameter difference:"
        f" {max_diff:.3f} sigma"
    )
    cold = np.zeros_like(start)
    cold[:3] = 1.0  # identity scale, zero offsets, angles and coefficients
    t_cold, est_cold = best_of(1, lambda: ml_fit(s, start=cold))
    t_cold_base, base_cold = best_of(
        1, lambda: least_squares(residual, cold, jac="2-point", method="trf", x_scale="jac")
    )
    print(
        f"from a cold start (identity, zeros): ours {t_cold * 1000:.1f} ms, scipy"
        f" {t_cold_base * 1000:.1f} ms ({base_cold.nfev} evaluations):"
        f" {t_cold_base / t_cold:.1f}x; same optimum:"
        f" {np.allclose(est_cold.p, est.p, atol=1e-6)}"
    )
    print(
        f"peak traced memory of the fit: {peak / 2**20:.1f} MiB"
        f" (Jacobian alone {s.n * 24 * 8 / 2**20:.1f} MiB)"
    )

    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "bench.csv"
        cols = {f"m{a}": s.measured_ut[:, i] for i, a in enumerate("xyz")}
        cols["b"] = s.field_magnitude_ut
        cols |= {ch: s.telemetry[:, j] for j, ch in enumerate(s.channels)}
        write_columns(csv, cols)
        cmd = [sys.executable, "-m", "rig.cli", "-q", "calibrate", str(csv), "--measured",
               "mx,my,mz", "--field-magnitude", "b", "--telemetry", ",".join(s.channels),
               "--out", str(Path(tmp) / "r.json")]  # fmt: skip
        walls = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True)
            walls.append(time.perf_counter() - t0)
        rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import numpy, scipy.linalg"], check=True)
        t_import = time.perf_counter() - t0
    print(
        f"rig calibrate on the {s.n}-row CSV: {min(walls):.3f} s wall (target < 1 s),"
        f" peak RSS {rss:.0f} MiB; python+numpy+scipy start-up alone {t_import:.3f} s"
    )
    ok = ratio >= 10.0 and min(walls) < 1.0
    print("PASS" if ok else "MISS")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
