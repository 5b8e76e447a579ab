"""The uncertainty budget over many simulated DUT runs: does the combined sigma match the errors?

First the shipped ``rig/shipped_procedures/cage-field-map.yaml`` runs once on a simulated cage (the operator
played: the reference moved to each position asked) and leaves the cage calibration record with
its field maps, as a lab has one record for its cage. Then each DUT run is the acceptance
procedure's calibration part (cage characterization, the two sphere sweeps with and without the
harness currents, the vector calibration with current-to-bias) on a simulated cage of its own: a
seed of its own (noise, traffic, flicker, supply drift), the reference's certificate off by a
fresh draw within the 1-sigma it states (50 ppm, 20 and 30 arcsec), and a lab gradient drawn
with the 1-sigma ``[cage] ambient_gradient_nt_per_m`` states (each run a lab of its own), through
the real wire protocols, the record in use. Per reported value (Springmann, current-to-bias,
mounting) it prints the rms error over the rms combined sigma (goal 0.8-1.2) and over the rms
statistical sigma alone (the cage terms left out: how overconfident the old numbers were), and
the share within 1.96 combined sigma.

The runs go on Dask (``distributed``): a local cluster of one worker process per core, or
``--scheduler ADDRESS``. Each run takes about a minute and a half of cage time, bound by the
simulated cage's real time rather than the CPU (a quarter of a core each): ``--workers 4`` to 6
suit two cores. 50 runs with 2 workers: 42 minutes.

Run: ``nice .venv/bin/python bench/bench_cage_budget.py [--runs 50] [--workers 2]``.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from rig.procedure_files import PROCEDURES_DIR

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench.dask_runs

ROOT = Path(__file__).resolve().parents[1]
GRADIENT_SIGMA_NT_PER_M = 15.0
DUT_PROCEDURE = """\
procedure: DUT calibration (the acceptance procedure's calibration part)
magnetometers: {dut: dut, reference: reference}
loads: [load_bus, load_panel]
steps:
  - characterize_cage: {amplitude_a: 1.0, samples: 10, repeats: 1}
    name: cage model
  - sphere_sweep: {directions: 48, magnitude_ut: [15, 45], dwell_s: 0.8, seed: 3}
    name: sweep with currents
    loads:
      load_bus: {steps: {levels_a: [0.0, 0.8, 0.0, 1.6], dwell_s: 2.4}}
      load_panel: {steps: {levels_a: [0.0, 0.0, 2.0, 1.0, 2.5], dwell_s: 3.2}}
  - sphere_sweep: {directions: 24, magnitude_ut: [25, 40], dwell_s: 0.8, seed: 4}
    name: sweep at zero current
  - calibrate: {model: vector, telemetry: [load_bus, load_panel], steps: [sweep with currents, sweep at zero current]}
    name: vector calibration
"""


def rig_toml(cage: Any, cfg: Any, record: Path) -> str:
    """The simulated rig's configuration with the cage calibration record at ``record``."""
    from rig.sim_rig import sim_rig_config

    text = sim_rig_config(cage.endpoints_document(), cfg)
    return text.replace('calibration = "cage-calibration.json"', f'calibration = "{record}"', 1)


def field_map_record(folder: Path) -> Path:
    """Run the field map procedure once (the operator played) and return the record it wrote."""
    from rig.config import load_rig_config
    from rig.engine.runner import Runner
    from rig.procedure.language import parse_procedure
    from sim.cage import SimulatedCage
    from sim.config import load_config

    record = folder / "cage.json"
    cfg = load_config()
    with SimulatedCage(cfg) as cage:
        (folder / "rig.toml").write_text(rig_toml(cage, cfg, record))

        def operator(question: str) -> bool:
            found = re.findall(r"[xyz] ([+-][\d.]+) cm", question)
            if len(found) == 3:
                cage.physics.move("reference", tuple(float(v) / 100.0 for v in found))
            return True

        procedure = parse_procedure(PROCEDURES_DIR / "cage-field-map.yaml")
        outcome = Runner(procedure, load_rig_config(folder / "rig.toml"), folder / "runs",
                         i2c_bus=cage.i2c_bus, confirm=operator, live=False).run()  # fmt: skip
    if outcome.exit_code != 0 or not record.exists():
        raise RuntimeError(f"the field map procedure did not leave a record: {outcome.reason}")
    return record


def drawn_gradient(rng: np.random.Generator) -> tuple[tuple[float, ...], ...]:
    """A lab gradient (uT/m): symmetric and traceless (curl- and divergence-free), each component
    with 1-sigma ``GRADIENT_SIGMA_NT_PER_M``."""
    sigma = GRADIENT_SIGMA_NT_PER_M / 1000.0
    diag = rng.standard_normal(3)
    diag = (diag - diag.mean()) * np.sqrt(1.5) * sigma
    g = np.diag(diag)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        g[i, j] = g[j, i] = sigma * rng.standard_normal()
    return tuple(tuple(float(v) for v in row) for row in g)


def truth_values(cfg: Any, channels: list[str]) -> np.ndarray:
    """The DUT's truth in the result's reported order (Springmann, k per channel, mounting)."""
    dut = cfg.magnetometer("dut")
    values = [*dut.scale, *dut.offset_ut, *dut.nonorth_deg]
    for ch in channels:
        values += list(dut.k_ut_per_a.get(ch, (0.0, 0.0, 0.0)))
    return np.array([*values, *dut.mounting_deg], float)


def flat(block: dict[str, Any], channels: list[str]) -> np.ndarray:
    """A result's ``sigma``-shaped block, flat in the reported order."""
    values = list(block["springmann"].values())
    for ch in channels:
        values += list(block["k_ut_per_unit"][ch])
    return np.array([*values, *block["mounting_deg"]], float)


def one_run(seed: int, record_text: str) -> dict[str, Any]:
    """One DUT calibration on a fresh simulated cage (seed ``seed``) with the record in use."""
    from rig.config import load_rig_config
    from rig.engine.runner import Runner
    from rig.procedure.language import parse_procedure
    from sim.cage import SimulatedCage
    from sim.config import load_config

    rng = np.random.default_rng([seed, 28])
    base = load_config()
    cfg = replace(base, seed=2000 + seed,
                  ambient=replace(base.ambient, gradient_ut_per_m=drawn_gradient(rng)))  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="cage-budget-") as tmp, SimulatedCage(cfg) as cage:
        folder = Path(tmp)
        record = folder / "cage.json"
        record.write_text(record_text)
        (folder / "rig.toml").write_text(rig_toml(cage, cfg, record))
        (folder / "dut.yaml").write_text(DUT_PROCEDURE)
        outcome = Runner(parse_procedure(folder / "dut.yaml"), load_rig_config(folder / "rig.toml"),
                         folder / "runs", i2c_bus=cage.i2c_bus, live=False).run()  # fmt: skip
    if outcome.exit_code not in (0, 1):
        return {"failed": f"run {seed}: {outcome.reason}"}  # counted, not judged
    vec = outcome.results["vector calibration"]
    channels = list(vec["channels"])
    value = np.array([*vec["springmann"].values(),
                      *(v for ch in channels for v in vec["correction"]["k_ut_per_unit"][ch]),
                      *vec["mounting"]["rotation_vector_deg"]], float)  # fmt: skip
    error = value - truth_values(cfg, channels)
    return {"error": error, "combined": flat(vec["combined_sigma"], channels),
            "statistical": flat(vec["sigma"], channels), "channels": channels,
            "left_out": vec["uncertainty_budget"]["left_out"],
            "groups": list(vec["uncertainty_budget"]["groups"])}  # fmt: skip


def names(channels: list[str]) -> list[str]:
    out = ["a", "b", "c", "x0_ut", "y0_ut", "z0_ut", "rho_deg", "phi_deg", "lambda_deg"]
    out += [f"k[{ch}].{ax}" for ch in channels for ax in "xyz"]
    return out + [f"mounting_{ax}_deg" for ax in "xyz"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=50, help="simulated DUT runs")
    from bench.dask_runs import add_dask_arguments, map_on_dask

    add_dask_arguments(parser)
    args = parser.parse_args()

    start = time.monotonic()
    folder = Path(tempfile.mkdtemp(prefix="cage-budget-map-"))
    try:
        record_text = field_map_record(folder).read_text()
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    mapped = time.monotonic() - start
    results = map_on_dask(
        one_run,
        range(args.runs),
        [record_text] * args.runs,
        workers=args.workers,
        scheduler=args.scheduler,
    )
    return summary(results, mapped, time.monotonic() - start)


def summary(results: list[dict[str, Any]], mapped_s: float, wall_s: float) -> int:
    """Print the table; 0 when every ratio of spread to combined sigma is within 0.8-1.2."""
    for why in [r["failed"] for r in results if "failed" in r]:
        print(f"left out (the run did not finish): {why}")
    results = [r for r in results if "failed" not in r]
    err = np.array([r["error"] for r in results])
    comb = np.array([r["combined"] for r in results])
    stat = np.array([r["statistical"] for r in results])
    print(f"\nfield map {mapped_s:.0f} s; {len(results)} DUT runs, {wall_s:.0f} s in all;"
          f" budget groups: {', '.join(results[0]['groups'])}; left out:"
          f" {'; '.join(results[0]['left_out']) or 'nothing'}")  # fmt: skip
    print(f"  {'value':<22} {'rms err/comb':>12} {'rms err/stat':>12} {'<=1.96 comb':>11}"
          f" {'rms comb/stat':>13}")  # fmt: skip
    ok = True
    for i, name in enumerate(names(results[0]["channels"])):
        spread = float(np.sqrt(np.mean(err[:, i] ** 2)))
        ratio = spread / float(np.sqrt(np.mean(comb[:, i] ** 2)))
        ratio_stat = spread / float(np.sqrt(np.mean(stat[:, i] ** 2)))
        within = 100 * np.mean(np.abs(err[:, i]) <= 1.96 * comb[:, i])
        flag = "" if 0.8 <= ratio <= 1.2 else "  <- outside 0.8-1.2"
        ok &= not flag
        print(f"  {name:<22} {ratio:12.2f} {ratio_stat:12.2f} {within:10.0f}%"
              f" {np.sqrt(np.mean(comb[:, i] ** 2) / np.mean(stat[:, i] ** 2)):13.2f}{flag}")  # fmt: skip
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
