"""Uncertainty audit: is the reported sigma true in every scenario the calibration core serves?

For each scenario of ``rig.calibration.uncertainty_audit.SCENARIOS`` - the vector fit of the synthetic cage
sweep (2000 samples, two load channels, 0.05 uT) under white noise, AR(1) noise with correlation
times of 1, 3, 10 and 30 samples and Student t with 3 dof; the scalar ``ml`` fit of the same
sweep from |h| only; the TRMM orbit of Crassidis, Lai and Harman (402 km, 35 deg, Earth pointing,
IGRF, |B| 19.6-42.6 uT, 2880 samples, 0.05 uT); a uniform hemisphere of a constant 47 uT field
(5000 samples, 0.2 uT: fitted with a warning); telemetry delays with smooth currents and with step
currents at random times and on the sample grid (a CSV: the telemetry column is the current at the
sample times; each draw has its own currents and true delays); temperature coefficients (a thermal
soak, 4000 samples) - ``--draws`` draws, each fitted through ``rig.calibration.calibrate`` with the
scenario's options exactly as ``rig calibrate`` fits. Per parameter it prints the rms of
``(estimate - truth) / sigma`` (goal 0.8-1.25), the 95th percentile of ``|error| / sigma`` (1.96
for honest Gaussian errors), the share of draws within 1.96 sigma (95 % for them) and the share
of draws beyond 4 sigma (goal at most 0.5 %), and flags what is outside the goal; per scenario
the wall time and the workers' compute time.

The draws run on Dask (``distributed``), the project's rule for Monte Carlo studies: a local
cluster of one single-threaded worker process per core by default, or the lab cluster's scheduler
with ``--scheduler tcp://HOST:8786`` (its workers need this repository installed, as
``pip install -e .``, and should run with ``OPENBLAS_NUM_THREADS=1``). Each task is a chunk of
``--chunk`` draws; the data are made once per scenario here and scattered to the workers (the
delay scenarios make theirs per draw, on the workers). Draw ``k`` has seed ``k`` whatever the
chunking, so the figures are the same as ``rig.calibration.uncertainty_audit.audit`` gives in one process.

With ``--cli`` the TRMM scenarios (``ml``, ``twostep``, ``ekf``, ``ukf``) are fitted as a
technician fits them: each draw written to a CSV and calibrated by ``rig calibrate`` in a process
of its own, the estimates and sigmas read back from its ``--out`` result file; a draw the command
refuses (non-zero exit) is counted and printed, never dropped silently.

Run: ``nice -n 19 .venv/bin/python bench/bench_uncertainty_audit.py [--draws 200]
[--scenario NAME ...] [--scheduler ADDRESS] [--workers N] [--chunk 10] [--cli]``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rig.calibration.result import SPRINGMANN_JSON, springmann_json
from rig.calibration.uncertainty_audit import (
    SCENARIOS,
    Scenario,
    draw_chunk,
    draw_z,
    make_case,
    noisy_draw,
    refused,
    scenario,
    summary,
    timed,
)
from rig.errors import CalibrationError

if TYPE_CHECKING:
    from distributed import Client

RMS_GOAL = (0.8, 1.25)
BEYOND_4_GOAL = 0.005


def orbit_field(altitude_km: float, inclination_deg: float, t_s: np.ndarray) -> np.ndarray:
    """The TRMM scenario's body-frame field: a circular orbit, Earth pointing, IGRF (2003-06-01)."""
    from rig.steps.orbit import circular_orbit_track

    start = dt.datetime(2003, 6, 1)
    return circular_orbit_track(altitude_km, inclination_deg, start, t_s, "nadir").field_body_ut


def run_on_dask(
    client: Client, sc: Scenario, draws: int, chunk: int = 10, via_cli: bool = False
) -> tuple[tuple[str, ...], np.ndarray, float]:
    """Names, ``z`` (draws, P) and the summed task compute time (s) of ``draws`` draws of ``sc``
    on the cluster of ``client``, ``chunk`` draws per task (draw ``k`` has seed ``k``); with
    ``via_cli`` each draw through ``rig calibrate`` (:func:`cli_draw_z`; the compute time is then
    the workers' own, the CLI processes' not counted)."""
    case = None if sc.fresh_data else make_case(sc, 0, orbit_field)
    # hash=False: a key of its own (scenarios with the same data would share one, and the
    # previous scenario releasing it could drop it under this one)
    shared: Any = None if case is None else client.scatter(case, broadcast=True, hash=False)
    seeds = [list(range(k, min(k + chunk, draws))) for k in range(0, draws, chunk)]
    futures = [client.submit(_timed_chunk, shared, sc, s, via_cli, pure=False) for s in seeds]
    parts = client.gather(futures)
    names = next((n for n, _, _ in parts if n), ())
    # a chunk whose draws were all refused has no columns: rows of NaN
    z = np.vstack([z if z.shape[1] else np.full((len(z), len(names)), np.nan)
                   for _, z, _ in parts])  # fmt: skip
    return names, z, float(sum(t for _, _, t in parts))


def _timed_chunk(
    case: Any, sc: Scenario, seeds: list[int], via_cli: bool = False
) -> tuple[tuple[str, ...], Any, float]:
    start = time.process_time()
    names, z = draw_chunk(case, sc, seeds, cli_draw_z if via_cli else draw_z)
    return names, z, time.process_time() - start


CLI_SCENARIOS = ("TRMM orbit", "TRMM orbit, twostep", "TRMM orbit, ekf", "TRMM orbit, ukf")
"""Scenarios ``--cli`` can run: scalar fits of |h| without telemetry, delays or temperature."""


def cli_draw_z(case: Any, sc: Scenario, seed: int) -> tuple[tuple[str, ...], np.ndarray]:
    """One draw as a technician makes it: the draw's samples written to a CSV (time, raw x, y, z,
    reference |h|; uT, s), ``rig calibrate CSV --method M [--time t_s] --out RESULT.json`` run as
    its own process, and ``(estimate - truth) / sigma`` per Springmann parameter read back from
    the result file (angles in degrees there). A non-zero exit is a refused draw (its last line
    raised as a CalibrationError: counted, never silent)."""
    case, noisy = noisy_draw(case, sc, seed)
    rig = Path(sys.executable).with_name("rig")
    with tempfile.TemporaryDirectory(prefix="audit-cli-") as tmp:
        data, out = Path(tmp) / "draw.csv", Path(tmp) / "result.json"
        table = np.column_stack([case.time_s, noisy.measured_ut, noisy.field_magnitude_ut])
        np.savetxt(data, table, fmt="%.10g", delimiter=",", header="t_s,mx,my,mz,bmag",
                   comments="")  # fmt: skip
        cmd = [str(rig), "calibrate", str(data), "--measured", "mx,my,mz", "--field-magnitude",
               "bmag", "--method", sc.method, "--out", str(out), "-q"]  # fmt: skip
        if timed(sc):
            cmd += ["--time", "t_s"]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, check=False)
        if done.returncode != 0:
            lines = (done.stderr or done.stdout).strip().splitlines() or [f"exit {done.returncode}"]
            raise CalibrationError(lines[-1])
        result = json.loads(out.read_text(encoding="utf-8"))
    truth = springmann_json(case.truth.springmann)  # in the result file's keys and units
    keys = tuple(truth)
    estimate = np.array([result["springmann"][k] for k in keys])
    sigma = np.array([result["sigma"]["springmann"][k] for k in keys])
    return tuple(SPRINGMANN_JSON), (estimate - np.array([truth[k] for k in keys])) / sigma


def report(sc: Scenario, names: tuple[str, ...], z: np.ndarray, wall: float, cpu: float) -> bool:
    """Print one scenario's table; True when every parameter is within the goal."""
    print(f"\n{sc.name}: {z.shape[0]} draws of {sc.samples} samples, {sc.method} fit"
          f" ({wall:.0f} s wall, {cpu:.0f} s compute)")  # fmt: skip
    if refused(z):
        print(f"  refused by calibrate (CalibrationError) in {refused(z)} draws: left out")
    if not names:
        return False
    rms, p95, beyond4 = summary(z)
    fitted = z[~np.all(np.isnan(z), axis=1)]
    within = np.mean(np.abs(fitted) <= 1.96, axis=0)  # 95 % for honest Gaussian errors
    print(f"  {'parameter':<18}{'rms z':>8}{'p95 |z|':>9}{'<=1.96':>8}{'>4 sigma':>10}")
    ok = True
    for i, name in enumerate(names):
        inside = RMS_GOAL[0] <= rms[i] <= RMS_GOAL[1] and beyond4[i] <= BEYOND_4_GOAL
        ok &= bool(inside)
        flag = "" if inside else "  <- outside goal"
        print(f"  {name:<18}{rms[i]:>8.2f}{p95[i]:>9.2f}{100 * within[i]:>7.0f}%"
              f"{100 * beyond4[i]:>9.1f}%{flag}")  # fmt: skip
    any4 = float(np.mean(np.any(np.abs(fitted) > 4.0, axis=1)))
    print(f"  all parameters: rms z {np.min(rms):.2f}-{np.max(rms):.2f}, p95 |z|"
          f" {np.min(p95):.2f}-{np.max(p95):.2f}, worst >4 sigma {100 * np.max(beyond4):.1f}%;"
          f" draws with any |z| > 4: {100 * any4:.1f}%")  # fmt: skip
    return ok and any4 <= BEYOND_4_GOAL


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200, help="draws per scenario")
    ap.add_argument("--scenario", action="append", help="only these scenarios (by name)")
    ap.add_argument("--scheduler", help="a Dask scheduler's address (default: a local cluster)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                    help="local cluster: worker processes (default: the cores)")  # fmt: skip
    ap.add_argument("--chunk", type=int, default=10, help="draws per task")
    ap.add_argument("--cli", action="store_true",
                    help="fit each draw with 'rig calibrate' on a CSV, as its own process (the"
                         f" scalar scenarios without telemetry: {', '.join(CLI_SCENARIOS)})")  # fmt: skip
    args = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: bench/
    from bench.dask_runs import local_cluster, require_dask

    require_dask()
    from distributed import Client

    chosen = [scenario(n) for n in args.scenario] if args.scenario else list(SCENARIOS)
    if args.cli:
        other = [sc.name for sc in chosen if sc.name not in CLI_SCENARIOS]
        if other and args.scenario:
            ap.error(f"--cli runs only {', '.join(CLI_SCENARIOS)}, not {', '.join(other)}")
        chosen = [sc for sc in chosen if sc.name in CLI_SCENARIOS]
    cluster = None if args.scheduler else local_cluster(args.workers)
    outside = []
    with Client(args.scheduler or cluster) as client:
        print(f"Dask: {len(client.scheduler_info()['workers'])} workers at"
              f" {client.scheduler.address}")  # fmt: skip
        for sc in chosen:
            start = time.perf_counter()
            names, z, cpu = run_on_dask(client, sc, args.draws, args.chunk, args.cli)
            if not report(sc, names, z, time.perf_counter() - start, cpu):
                outside.append(sc.name)
    if cluster is not None:
        cluster.close()
    print(f"\noutside the goal: {', '.join(outside) if outside else 'none'}")
    return 1 if outside else 0


if __name__ == "__main__":
    raise SystemExit(main())
