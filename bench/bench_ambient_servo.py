"""The ambient servo over a long hold on the simulated cage: how well is the field at the DUT held?

``rig cage hold 0 0 0 --servo`` runs (the real command's code, over the wire) on the simulated cage
with its realistic lab field on: slow drift, the daily variation, 1/f noise and traffic (vehicles in
the street 15 m away, 8 m from the outside reference's place too). The command prints the rms of
10 s means of the inner reference about the target, servoed, and the same without the servo,
measured in the same run (the inner reference less the trims' field). Beside it, this script
reads the simulator's truth, the field where the DUT sits less the 50 Hz mains ripple (which a
0.1 s reading would alias into its means), every 0.1 s: its rms of 10 s means
about their mean over the hold (the servo's stability at the DUT) and about the target (with the
static difference between the reference's place and the DUT's, which the uncertainty budget
carries).

Run: ``nice .venv/bin/python bench/bench_ambient_servo.py [--duration 3600]`` (real time: the
simulator runs at the wall clock).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def block_means(t: np.ndarray, values: np.ndarray, block_s: float) -> np.ndarray:
    blocks = np.floor((t - t[0]) / block_s).astype(int)
    return np.array([values[blocks == b].mean(axis=0) for b in np.unique(blocks)
                     if np.sum(blocks == b) >= 10])  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=3600.0, help="hold (s, real time)")
    parser.add_argument("--seed", type=int, default=7, help="the simulated cage's seed")
    args = parser.parse_args()
    from dataclasses import replace

    from rig.cli.cage_hold import run_hold
    from sim.config import load_config
    from tests.simcage import sim_cage

    cfg = replace(load_config(), seed=args.seed)
    with (
        tempfile.TemporaryDirectory(prefix="servo-") as tmp,
        sim_cage(Path(tmp), cfg) as (cage, rig_toml),
    ):
        truth: list[tuple[float, np.ndarray]] = []
        stop = threading.Event()

        def watch() -> None:
            while not stop.is_set():
                t = time.monotonic()  # the servo is not for the 50 Hz mains: it is left out
                physics = cage.physics
                truth.append(
                    (t, physics.field_at_ut("dut", t, noise=False) - physics.mains_ripple_ut(t))
                )
                time.sleep(0.1)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        rc = run_hold(rig_toml, [0.0, 0.0, 0.0], True, args.duration, 0.5, 10.0,
                      Path(tmp) / "hold.csv", True)  # fmt: skip
        returned = time.monotonic()
        stop.set()
        watcher.join()
    t = np.array([r[0] for r in truth])
    field = np.array([r[1] for r in truth])
    keep = (t > returned - args.duration + 5.0) & (t < returned - 6.0)  # the hold, not the ramps
    means = block_means(t[keep], field[keep], 10.0)
    about_mean = 1000 * means.std(axis=0)
    about_target = 1000 * np.sqrt(np.mean(means**2, axis=0))
    print(f"simulator's truth at the DUT, {len(means)} 10 s means: rms about their mean"
          f" {', '.join(f'{a} {v:.2f}' for a, v in zip('xyz', about_mean, strict=True))} nT;"
          f" about the target {', '.join(f'{a} {v:.2f}' for a, v in zip('xyz', about_target, strict=True))} nT")  # fmt: skip
    return rc


if __name__ == "__main__":
    sys.exit(main())
