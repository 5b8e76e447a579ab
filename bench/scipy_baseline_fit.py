"""Whole-process baseline for ``rig calibrate``: read the same CSV, fit the same scalar model with
``scipy.optimize.least_squares`` (finite-difference Jacobian), as a scipy user would.

The model and weights are the rig's maximum-likelihood ones: residual ``|W (m - o - K^T u)| - |h|``
in the Springmann-Cutler parameters, weighted by the inverse noise gain ``1/|W^T n_hat|`` (1 at the
cold start, refreshed once at the first solution), covariance from the solver's Jacobian. Started
cold (identity scale, zero offsets, angles and coefficients): the linear start is rig's own code.

Usage: python bench/scipy_baseline_fit.py DATA.csv --measured mx,my,mz --field-magnitude b
       --telemetry c1,c2,... [--out RESULT.json]
Prints the parameters' cost; ``bench/bench_scalar_fit.py`` times it as a subprocess.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from scipy.optimize import least_squares


def lower(x: np.ndarray) -> np.ndarray:
    a, b, c, rho, phi, lam = x[0], x[1], x[2], x[6], x[7], x[8]
    return np.array(
        [
            [a, 0.0, 0.0],
            [b * np.sin(rho), b * np.cos(rho), 0.0],
            [c * np.sin(lam), c * np.sin(phi) * np.cos(lam), c * np.cos(phi) * np.cos(lam)],
        ]
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("data")
    ap.add_argument("--measured", required=True)
    ap.add_argument("--field-magnitude", required=True)
    ap.add_argument("--telemetry", default="")
    ap.add_argument("--out")
    args = ap.parse_args()
    with open(args.data, encoding="utf-8") as fh:
        header = fh.readline().strip().split(",")
    measured = args.measured.split(",")
    channels = [c for c in args.telemetry.split(",") if c]
    wanted = [header.index(c) for c in [*measured, args.field_magnitude, *channels]]
    data = np.loadtxt(args.data, delimiter=",", skiprows=1, usecols=wanted, ndmin=2)
    m, h, u = data[:, :3], data[:, 3], data[:, 4:]

    def corrected(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w = np.linalg.inv(lower(x))
        return w, (m - x[3:6] - u @ x[9:].reshape(-1, 3)) @ w.T

    def gain(x: np.ndarray) -> np.ndarray:
        w, g = corrected(x)
        return np.linalg.norm((g / np.linalg.norm(g, axis=1)[:, None]) @ w, axis=1)

    x = np.zeros(9 + 3 * len(channels))
    x[:3] = 1.0
    for _ in range(2):  # the cold start's weights (all 1), then refreshed once at its solution
        sw = 1.0 / gain(x)

        def residual(x: np.ndarray, sw: np.ndarray = sw) -> np.ndarray:
            return (np.linalg.norm(corrected(x)[1], axis=1) - h) * sw

        sol = least_squares(residual, x, jac="2-point", method="trf", x_scale="jac")
        x = sol.x
    dof = max(m.shape[0] - x.size, 1)
    variance = float(sol.fun @ sol.fun) / dof
    cov = variance * np.linalg.pinv(sol.jac.T @ sol.jac)
    out = {
        "p": x.tolist(),
        "sigma": np.sqrt(np.diag(cov)).tolist(),
        "cost": float(sol.fun @ sol.fun),
    }
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            json.dump(out, fh)
    print(f"cost {out['cost']:.6e} after {sol.nfev} evaluations")
    return 0


if __name__ == "__main__":
    sys.exit(main())
