"""Uncertainty audit: is the reported sigma true for white, coloured and heavy-tailed noise?

For each scenario of ``rig.calibration.audit.SCENARIOS`` (white; AR(1) noise with correlation
times of 1, 3, 10 and 30 samples; Student t with 3 dof), ``--draws`` noise draws on the same
synthetic cage sweep (2000 samples, two load channels, 0.05 uT marginal noise per axis), each
fitted by the default vector method exactly as ``rig calibrate`` fits (whiteness test, HAC sigmas
when correlated; ADR 0025). Per parameter it prints the rms of ``(estimate - truth) / sigma``
(goal 0.8-1.25), the 95th percentile of ``|error| / sigma`` (1.96 for honest Gaussian errors)
and the share of draws beyond 4 sigma (goal under 0.5 %).

The draws run one after another in this process: the repository has no Monte Carlo cluster
guidance (no Dask or other scheduler is used anywhere), and 1200 fits take minutes.

Run: ``.venv/bin/python bench/bench_uncertainty_audit.py [--draws 200] [--samples 2000]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from rig.calibration.audit import SCENARIOS, audit, summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200, help="noise draws per scenario")
    ap.add_argument("--samples", type=int, default=2000, help="samples per fit")
    ap.add_argument("--scenario", action="append", help="only these scenarios (by name)")
    args = ap.parse_args()
    for sc in SCENARIOS:
        if args.scenario and sc.name not in args.scenario:
            continue
        start = time.perf_counter()
        names, z = audit(sc, args.draws, args.samples)
        rms, p95, beyond4 = summary(z)
        wall = time.perf_counter() - start
        print(f"\n{sc.name}: {args.draws} draws of {args.samples} samples ({wall:.0f} s)")
        print(f"  {'parameter':<16}{'rms z':>8}{'p95 |z|':>9}{'>4 sigma':>10}")
        for i, name in enumerate(names):
            flag = "" if 0.8 <= rms[i] <= 1.25 and beyond4[i] <= 0.005 else "  <- outside goal"
            print(f"  {name:<16}{rms[i]:>8.2f}{p95[i]:>9.2f}{100 * beyond4[i]:>9.1f}%{flag}")
        print(f"  all parameters: rms z {np.min(rms):.2f}-{np.max(rms):.2f}, p95 |z|"
              f" {np.min(p95):.2f}-{np.max(p95):.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
