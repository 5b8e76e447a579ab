"""Coil constants by the scalar method, over many simulated procedures: are the reported sigmas
true, and how do they compare with the turned reference's?

Each procedure is the shipped ``rig/shipped_procedures/cage-metrology-scalar.yaml`` run by the engine on a
simulated cage of its own (a seed of its own: noise, lab field, traffic; Biot-Savart coils, supply
drift), through the real wire protocols: the cesium sensor behind its CM-201 counter at the centre
(0.02 nT noise, 1.4 nT offset, 0.5 nT heading error, dead zones of 10 deg). Per procedure
``(estimate - truth) / sigma`` of the three coil constants and the three skews, the truth being the
simulator's coils where the sensor sits (times the supplies' gains). Prints per parameter the rms
of z (goal 0.8-1.25), the 95th percentile of |z|, the share within 1.96 sigma and the median sigma.

The procedures run on Dask (``distributed``): a local cluster, or ``--scheduler ADDRESS``.

Run: ``nice .venv/bin/python bench/bench_coil_scalar.py [--procedures 50] [--workers 4]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench.*

from bench.bench_coil_axes import NAMES, summarize, z_of
from rig.procedure_files import PROCEDURES_DIR

PROCEDURE = PROCEDURES_DIR / "cage-metrology-scalar.yaml"


def one_procedure(seed: int) -> dict[str, Any]:
    """Run the scalar procedure on a fresh simulated cage (seed ``seed``); z and sigmas."""
    from rig.config import load_rig_config
    from rig.engine.runner import Runner
    from rig.procedure.language import parse_procedure
    from rig.sim_rig import sim_rig_config
    from sim.cage import SimulatedCage
    from sim.config import load_config

    cfg = replace(load_config(), seed=2000 + seed)
    truths: list[np.ndarray] = []
    with tempfile.TemporaryDirectory(prefix="coil-scalar-") as tmp, SimulatedCage(cfg) as cage:
        folder = Path(tmp)
        rig_toml = folder / "rig.toml"
        rig_toml.write_text(sim_rig_config(cage.endpoints_document(), cfg))

        def operator(question: str) -> bool:
            return True

        runner = Runner(parse_procedure(PROCEDURE), load_rig_config(rig_toml), folder / "runs",
                        i2c_bus=cage.i2c_bus, confirm=operator, live=False)  # fmt: skip
        outcome = runner.run()
        truths.append(cage.physics.coil_matrix_at["cesium"] * cage.physics.coil_gains())
    if outcome.exit_code not in (0, 1):
        return {"failed": f"procedure {seed}: {outcome.reason}"}
    r = outcome.results["scalar coils"]
    return z_of(r, truths[-1]) | {"chi2": r["chi2_per_dof"], "points": r["points"]}


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
    print(f"chi-square per dof (median) {np.median([r['chi2'] for r in results if 'chi2' in r]):.2f},"
          f" points {np.median([r['points'] for r in results if 'points' in r]):.0f}")  # fmt: skip
    return summarize(results, time.monotonic() - start, NAMES)


if __name__ == "__main__":
    sys.exit(main())
