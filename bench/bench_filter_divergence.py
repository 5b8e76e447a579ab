"""Sequential filters never diverge silently: a Monte Carlo of TRMM-like runs per filter.

The scenario of Crassidis, Lai and Harman's Table 1 (circular 402 km orbit at 35 deg, one turn
about body y per orbit, IGRF, 0.5 mG noise, a sample every 10 s for 8 h), with the truth drawn
per run around the paper's (bias components 50, 30, 60 mG +- ``--bias-spread``, D entries 0.05,
0.10, 0.05 +- ``--d-spread``) and the filters started from zero as ``rig calibrate --method ekf|ukf``
starts them (``--filter-variant energy`` and ``paper``). Every run goes through the same
``run_filter`` as ``rig calibrate``: divergence detected from the innovations, re-initialization
from the batch estimate, refusal of a final answer far worse than the batch fit.

Per filter it prints: runs re-initialized, runs refused (exit 2 in ``rig calibrate``), answers
given and wrong (any bias component off by more than 2 mG or a D entry by more than 0.005, about
5x the batch fit's largest deviation), and the mean +- maximum deviation of the answers given,
next to the paper's Table 1 spreads. Goal: 0 wrong answers given (0 silent divergences).

Run: ``.venv/bin/python bench/bench_filter_divergence.py [--runs 100]``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import time
from dataclasses import dataclass, field

import numpy as np
from bench_realtime_filters import B_TRUE_UT, D_TRUE, MG_PER_UT, NOISE_UT, PAPER, ROWS, b_and_d

from rig.calibration.residuals import Samples
from rig.calibration.sequential.realtime import FilterOptions, run_filter
from rig.errors import CalibrationError
from rig.steps.orbit import circular_orbit_track

WRONG_B_MG = 2.0
WRONG_D = 0.005
FILTERS = {
    "ekf (energy, default)": FilterOptions("ekf", "energy"),
    "ukf (energy, default)": FilterOptions("ukf", "energy"),
    "ekf (paper)": FilterOptions("ekf", "paper", bias_sigma_ut=np.sqrt(5.0), e_sigma=np.sqrt(1e-3)),
    "ukf (paper)": FilterOptions("ukf", "paper", bias_sigma_ut=np.sqrt(5.0), e_sigma=np.sqrt(1e-3)),
}
PAPER_ROW = {"ekf (paper)": "EKF", "ukf (paper)": "UF"}


@dataclass
class Tally:
    """One filter's outcomes over the runs."""

    reinitialized: int = 0
    refused: int = 0
    wrong: int = 0
    answers: list[np.ndarray] = field(default_factory=list)
    seconds: float = 0.0


def truth(
    rng: np.random.Generator, b_spread_mg: float, d_spread: float
) -> tuple[np.ndarray, np.ndarray]:
    """Bias (uT) and symmetric D of one run."""
    b = B_TRUE_UT + rng.uniform(-b_spread_mg, b_spread_mg, 3) / MG_PER_UT
    a = rng.uniform(-d_spread, d_spread, (3, 3))
    return b, D_TRUE + 0.5 * (a + a.T)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100, help="Monte Carlo runs per filter")
    ap.add_argument("--bias-spread", type=float, default=100.0, help="+- mG on each bias component")
    ap.add_argument("--d-spread", type=float, default=0.05, help="+- on each D entry")
    args = ap.parse_args()
    t = np.arange(0.0, 8 * 3600.0, 10.0)
    track = circular_orbit_track(402.0, 35.0, dt.datetime(2003, 6, 1), t, "nadir")
    field_ut = track.field_body_ut
    mag = np.linalg.norm(field_ut, axis=1)
    print(f"{args.runs} runs per filter, {t.size} samples each, bias 50/30/60 mG +- {args.bias_spread:g},"
          f" D +- {args.d_spread:g}, noise {NOISE_UT * MG_PER_UT:.1f} mG")  # fmt: skip
    tallies = {name: Tally() for name in FILTERS}
    wall0 = time.perf_counter()
    for run in range(args.runs):
        rng = np.random.default_rng(5000 + run)
        b, d = truth(rng, args.bias_spread, args.d_spread)
        eps = NOISE_UT * rng.standard_normal(field_ut.shape)
        m = np.linalg.solve(np.eye(3) + d, (field_ut + b + eps).T).T
        s = Samples.build(m, field_magnitude_ut=mag)
        want = np.concatenate([b * MG_PER_UT, d[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]])
        for name, opts in FILTERS.items():
            tally = tallies[name]
            t0 = time.perf_counter()
            try:
                est, history = run_filter(s, opts, NOISE_UT)
            except CalibrationError:
                tally.refused += 1
                continue
            finally:
                tally.seconds += time.perf_counter() - t0
            if any("re-initialized" in n for n in est.notes):
                tally.reinitialized += 1
            got = b_and_d(history.final_theta)
            err = got - want
            if np.abs(err[:3]).max() > WRONG_B_MG or np.abs(err[3:]).max() > WRONG_D:
                tally.wrong += 1
            tally.answers.append(err)
        print(
            f"\r  run {run + 1}/{args.runs} ({time.perf_counter() - wall0:.0f} s)",
            end="",
            flush=True,
        )
    print(
        "\n\nfilter                  re-initialized  refused (exit 2)  answers  wrong answers given"
    )
    for name, tl in tallies.items():
        print(f"  {name:22s} {tl.reinitialized:14d} {tl.refused:17d} {len(tl.answers):8d}"
              f" {tl.wrong:20d}")  # fmt: skip
    silent = sum(tl.wrong for tl in tallies.values())
    print(f"\nsilent divergences (wrong answers given, all filters): {silent}   (goal 0)")
    print("\nerror of the answers given: mean +- max deviation (truth subtracted per run);"
          " paper's Table 1 spread in brackets")  # fmt: skip
    for name, tl in tallies.items():
        if not tl.answers:
            continue
        errs = np.asarray(tl.answers)
        mean = errs.mean(axis=0)
        dev = np.abs(errs - mean).max(axis=0)
        print(f"\n{name}   ({1000 * tl.seconds / args.runs:.0f} ms per run)")
        for i, row in enumerate(ROWS):
            fmt = "{:8.3f}" if i < 3 else "{:8.4f}"
            line = f"  {row:4s} {fmt.format(mean[i])} +- {fmt.format(dev[i])}{' mG' if i < 3 else '   '}"
            if name in PAPER_ROW:
                pd = PAPER[PAPER_ROW[name]][i][1]
                line += f"   [paper +- {fmt.format(pd)}, ratio {dev[i] / pd:5.2f}]"
            print(line)
    return 0 if silent == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
