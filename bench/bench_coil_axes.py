"""Coil axes by the turned reference, over many simulated procedures: are the reported sigmas true?

Each procedure is the shipped ``rig/shipped_procedures/cage-metrology.yaml`` run by the engine on a simulated
cage of its own (a seed of its own: noise, lab field, traffic; Biot-Savart coils, supply drift),
through the real wire protocols, with the operator played here: at each prompt the simulated
reference is turned to the position asked, off by 30 arcsec (1-sigma per axis, seeded) as a real
fixture's turns are. Per procedure ``(estimate - truth) / sigma`` of the three coil constants and
the three skews, the truth being the simulator's coils where the reference sits (times the
supplies' gains). Prints per parameter the rms of z (goal 0.8-1.25), the 95th percentile of |z|,
the share within 1.96 sigma, and the median sigma and largest error.

The procedures run on Dask (``distributed``): a local cluster of one worker process per core, or
``--scheduler ADDRESS``. Each takes about a minute of cage time.

Run: ``nice .venv/bin/python bench/bench_coil_axes.py [--procedures 50] [--workers 2]``.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from rig.procedure_files import PROCEDURES_DIR

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench.dask_runs

PROCEDURE = PROCEDURES_DIR / "cage-metrology.yaml"
FIXTURE_ERROR_ARCSEC = 30.0
NAMES = ("constant x", "constant y", "constant z", "skew xy", "skew xz", "skew yz")


def skews_arcsec(k: np.ndarray) -> np.ndarray:
    """The angles between the coil axes (columns of ``k``) minus 90 degrees (arcsec)."""
    unit = k / np.linalg.norm(k, axis=0)
    return np.array([math.degrees(math.pi / 2 - math.acos(unit[:, i] @ unit[:, j])) * 3600
                     for i, j in ((0, 1), (0, 2), (1, 2))])  # fmt: skip


def one_procedure(seed: int) -> dict[str, Any]:
    """Run the metrology procedure on a fresh simulated cage (seed ``seed``); z and sigmas."""
    from rig.cage.coil_axes import DEFAULT_POSITIONS, rotation
    from rig.config import load_rig_config
    from rig.engine.runner import Runner
    from rig.procedure.language import parse_procedure
    from rig.sim_rig import sim_rig_config
    from sim.cage import SimulatedCage
    from sim.config import load_config

    rng = np.random.default_rng([seed, 35])
    cfg = replace(load_config(), seed=1000 + seed)
    truth: dict[str, np.ndarray] = {}
    with tempfile.TemporaryDirectory(prefix="coil-axes-") as tmp, SimulatedCage(cfg) as cage:
        folder = Path(tmp)
        rig_toml = folder / "rig.toml"
        rig_toml.write_text(sim_rig_config(cage.endpoints_document(), cfg))

        def operator(question: str) -> bool:
            found = re.match(r"Fixture position (\d) of 4", question)
            if found:
                index = int(found[1]) - 1
                error = np.radians(FIXTURE_ERROR_ARCSEC / 3600) * rng.standard_normal(3)
                turn = DEFAULT_POSITIONS[index][1] @ rotation(error if index else np.zeros(3))
                cage.physics.magnetometers["reference"].set_turn(turn)
                truth["k"] = cage.physics.coil_matrix_at["reference"] * cage.physics.coil_gains()
            return True

        outcome = Runner(parse_procedure(PROCEDURE), load_rig_config(rig_toml), folder / "runs",
                         i2c_bus=cage.i2c_bus, confirm=operator, live=False).run()  # fmt: skip
    if outcome.exit_code not in (0, 1):
        return {"failed": f"procedure {seed}: {outcome.reason}"}  # counted, not fitted
    return z_of(outcome.results["coil axes"], truth["k"])


def z_of(r: dict[str, Any], k: np.ndarray) -> dict[str, Any]:
    """``(estimate - truth) / sigma`` of the constants and skews of result ``r`` against the true
    coil matrix ``k`` (columns: uT/A per coil), with the sigmas and errors."""
    consts = np.array([r["constants_ut_per_a"][a] for a in "xyz"])
    const_sigma = 1e-6 * consts * np.array([r["constants_sigma_ppm"][a] for a in "xyz"])
    skews = np.array([r["skew_arcsec"][p] for p in ("xy", "xz", "yz")])
    skew_sigma = np.array([r["skew_sigma_arcsec"][p] for p in ("xy", "xz", "yz")])
    error = np.concatenate([consts - np.linalg.norm(k, axis=0), skews - skews_arcsec(k)])
    sigma = np.concatenate([const_sigma, skew_sigma])
    return {"z": error / sigma, "sigma": sigma, "error": error,
            "relative": np.concatenate([1e6 * const_sigma / consts, skew_sigma])}  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--procedures", type=int, default=50, help="simulated procedures")
    from bench.dask_runs import add_dask_arguments, map_on_dask

    add_dask_arguments(parser)
    args = parser.parse_args()

    start = time.monotonic()
    results = map_on_dask(
        one_procedure, range(args.procedures), workers=args.workers, scheduler=args.scheduler
    )
    return summarize(results, time.monotonic() - start, NAMES)


def summarize(results: list[dict[str, Any]], wall_s: float, names: tuple[str, ...]) -> int:
    """Print per parameter the rms of z, the 95th percentile of |z|, the share within 1.96 and the
    median sigma; 0 when every rms z is within 0.8-1.25."""
    failed = [r["failed"] for r in results if "failed" in r]
    results = [r for r in results if "failed" not in r]
    for why in failed:
        print(f"left out (the run did not finish): {why}")
    z = np.array([r["z"] for r in results])
    rel = np.array([r["relative"] for r in results])
    print(f"\n{len(results)} procedures on the simulated cage in {wall_s:.0f} s")
    print(f"  {'parameter':<12} {'rms z':>6} {'p95 |z|':>8} {'<=1.96':>7} {'median sigma':>14}")
    ok = True
    for i, name in enumerate(names):
        rms = float(np.sqrt(np.mean(z[:, i] ** 2)))
        unit = "ppm" if i < 3 else "arcsec"
        flag = "" if 0.8 <= rms <= 1.25 else "  <- outside 0.8-1.25"
        ok &= not flag
        print(f"  {name:<12} {rms:6.2f} {np.percentile(np.abs(z[:, i]), 95):8.2f}"
              f" {100 * np.mean(np.abs(z[:, i]) <= 1.96):6.0f}% {np.median(rel[:, i]):9.1f} {unit}{flag}")  # fmt: skip
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
