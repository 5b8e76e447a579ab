"""The noise a calibration will see: the DUT's readings less the reference field, per DUT axis.

Measured beats stated, and measured where it matters beats measured at rest: the residuals of a
vector calibration of the same DUT (per axis: ``noise_axes_nt``, the noise its sigmas took: what its
hold means see) are that noise at the fields and currents of a sweep (a coil carrying more current
may add noise to its axis, which a hold at null field does not show); a ``null_field`` step's
``dut_paired_noise_nt`` is the noise at rest (the DUT's own, the reference's, and whatever the two
sample differently, such as mains ripple at different instants). So the floor is, in order: given on
the command line; the newest runs of the same DUT in the runs folder (their vector calibrations'
residuals pooled, else the newest null-field noise); the root sum square of the two devices' stated
``noise_nt`` (rig configuration); else unknown.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rig.config import RigConfig
from rig.errors import UserInputError
from rig.steps.null_field import NoiseFloorResult
from rig.steps.vocabulary import Procedure
from rig.store.run_store import RunReader, list_runs

RUNS_LOOKED_AT = 50
"""The newest runs searched for a measured noise floor."""
POOLED_RUNS = 5
"""The newest runs whose calibration residuals are pooled into the floor."""
REST_RUNS = 20
"""The newest runs whose null-field noises make a live filter's (their spread too: a live step
stops when its sigmas, which scale with that noise, meet their targets)."""


@dataclass(frozen=True)
class NoiseFloor:
    """Per DUT axis the rms of the DUT less the reference field (nT) and where it comes from."""

    axes_nt: tuple[float, float, float]
    source: str
    runs_nt: tuple[float, ...] = ()
    """Each earlier run's own figure (nT) when the floor pools several (their rms is the floor)."""
    runs_axes_nt: tuple[tuple[float, float, float], ...] = ()
    """Each earlier run's own figure per axis (nT), when the floor pools runs' residuals: an axis's
    noise moves between runs more than the three axes' rms does (the mains ripple each axis's
    samples happen to catch)."""

    @property
    def pair_nt(self) -> float:
        """The rms over the axes (nT)."""
        return math.sqrt(sum(v * v for v in self.axes_nt) / 3.0)


def even(nt: float, source: str) -> NoiseFloor:
    """The same noise ``nt`` on every axis."""
    return NoiseFloor((nt, nt, nt), source)


def pooled(runs_nt: list[float], source: str) -> NoiseFloor:
    """The rms of several runs' noises ``runs_nt`` (nT) on every axis, keeping each one."""
    rms = math.sqrt(sum(v * v for v in runs_nt) / len(runs_nt))
    return NoiseFloor((rms, rms, rms), source, tuple(runs_nt))


def noise_floor(proc: Procedure, cfg: RigConfig | None, runs_dir: Path | None,
                given_nt: float | None, exclude: str | None = None) -> NoiseFloor:  # fmt: skip
    """The noise floor the prediction uses (see the module's order; the runs without run id
    ``exclude``: a run predicting its own steps); UserInputError naming the fixes when none is
    known."""
    dut = proc.magnetometers.get("dut", "dut")
    if given_nt is not None:
        if not given_nt > 0:
            raise UserInputError(f"--noise-nt must be positive, got {given_nt:g}")
        return even(given_nt, "given (--noise-nt)")
    serial = proc.parameters.get("dut_serial") or None
    measured = measured_floor(runs_dir, dut, serial, exclude) if runs_dir is not None else None
    if measured is not None:
        return measured
    stated = _stated(cfg, dut, proc.magnetometers.get("reference"))
    if stated is not None:
        return stated
    raise UserInputError(
        f"no noise floor known for '{dut}': run a procedure with a null_field step on it once,"
        f" give its noise_nt (and the reference's) in the rig configuration, or --noise-nt"
    )


def measured_floor(runs_dir: Path, dut: str, serial: str | None = None,
                   exclude: str | None = None) -> NoiseFloor | None:  # fmt: skip
    """The noise the newest runs of the DUT measured (None if none): the residuals per axis of
    their last vector calibrations, pooled over up to :data:`POOLED_RUNS` runs (rms: a run's own
    figure varies with where its samples fall on the mains ripple), else the newest null-field
    noise paired with the reference. The DUT is the unit of serial ``serial`` on device ``dut``
    (issue 55: runs of any unit on that port had been pooled, a noisier unit predicted 14-31 %
    optimistic for its first 3-12 runs); a serial with no run yet: any unit on ``dut``, said."""
    if serial is not None:
        own = _measured(runs_dir, dut, serial, exclude)
        if own is not None:
            return own
        found = _measured(runs_dir, dut, None, exclude)
        if found is None:
            return None
        return dataclasses.replace(found, source=f"{found.source} (no run of serial {serial} yet:"
                                   " other units on that device)")  # fmt: skip
    return _measured(runs_dir, dut, None, exclude)


def _measured(runs_dir: Path, dut: str, serial: str | None,
              exclude: str | None = None) -> NoiseFloor | None:  # fmt: skip
    """:func:`measured_floor` from the runs of ``dut`` with DUT serial ``serial`` (None: any)."""
    residuals: list[tuple[float, ...]] = []
    rest: NoiseFloor | None = None
    for run_id, results in results_of(runs_dir, dut, serial, exclude):
        axes = _residual_axes(results)
        if axes is not None:
            residuals.append(axes)
            if len(residuals) == POOLED_RUNS:
                break
        elif rest is None:
            rest = _null_field(results, run_id)
    if residuals:
        pooled = np.sqrt(np.mean(np.square(residuals), axis=0))
        runs = f"{len(residuals)} run{'s' if len(residuals) > 1 else ''}"
        runs += f" of serial {serial}" if serial is not None else ""
        each = tuple(float(np.sqrt(np.mean(np.square(r)))) for r in residuals)
        return NoiseFloor((float(pooled[0]), float(pooled[1]), float(pooled[2])),
                          f"the vector calibration residuals of the newest {runs} of '{dut}'",
                          each, tuple((r[0], r[1], r[2]) for r in residuals))  # fmt: skip
    return rest


def rest_floor(runs_dir: Path | None, dut: str, serial: str | None = None,
               exclude: str | None = None) -> NoiseFloor | None:  # fmt: skip
    """The null-field noises of the DUT paired with the reference (what a live calibration's
    filter is given) in the newest :data:`REST_RUNS` runs that measured one, pooled with each
    run's kept; None if no run measured it. The DUT: the unit of serial ``serial`` on device
    ``dut`` when it has such runs, else any unit on ``dut`` (said)."""
    if runs_dir is None:
        return None
    for wanted in [serial, None] if serial is not None else [None]:
        found: list[NoiseFloor] = []
        for run_id, results in results_of(runs_dir, dut, wanted, exclude):
            floor = _null_field(results, run_id)
            if floor is not None:
                found.append(floor)
                if len(found) == REST_RUNS:
                    break
        if not found:
            continue
        whose = (f" of serial {serial}" if wanted is not None else
                 f" (no run of serial {serial} yet: other units on that device)" if serial else "")  # fmt: skip
        if len(found) < 2:
            return dataclasses.replace(found[0], source=found[0].source + whose)
        return pooled([f.pair_nt for f in found],
                      f"the null fields of the newest {len(found)} runs of '{dut}'{whose}")  # fmt: skip
    return None


def results_of(runs_dir: Path, dut: str, serial: str | None = None,
               exclude: str | None = None) -> Iterator[tuple[str, dict[str, Any]]]:  # fmt: skip
    """(run id, results) of the newest runs of device ``dut`` (at most :data:`RUNS_LOOKED_AT`
    runs looked at), newest first; of DUT serial ``serial`` only when given; never run
    ``exclude``."""
    for info in list_runs(runs_dir)[:RUNS_LOOKED_AT]:
        if info.run_id == exclude:
            continue
        if (info.meta.get("magnetometers") or {}).get("dut") != dut:
            continue
        if serial is not None and str(info.meta.get("dut_serial") or "") != serial:
            continue
        reader = RunReader(info.folder)
        try:
            results = reader.results()
        finally:
            reader.close()
        yield info.run_id, results


def _residual_axes(results: Mapping[str, Any]) -> tuple[float, ...] | None:
    """The last vector calibration's noise per axis among a run's results: as its sigmas took it
    (``noise_axes_nt``: what the hold means see, issue 55), else its residual rms."""
    for value in reversed(list(results.values())):
        if not isinstance(value, dict):
            continue
        axes = value.get("noise_axes_nt", value.get("residual_rms_axes_nt"))
        if isinstance(axes, list) and len(axes) == 3 and all(v > 0 for v in axes):
            return tuple(float(v) for v in axes)
    return None


def _null_field(results: Mapping[str, Any], run_id: str) -> NoiseFloor | None:
    """The last null-field noise paired with the reference among a run's results."""
    for name, value in reversed(list(results.items())):
        found = NoiseFloorResult.from_dict(value) if isinstance(value, dict) else None
        pair = found.pair_noise_nt("dut") if found is not None else None
        if pair is not None and pair > 0:
            return even(pair, f"measured at null field by '{name}' of run {run_id}")
    return None


def _stated(cfg: RigConfig | None, dut: str, reference: str | None) -> NoiseFloor | None:
    if cfg is None or dut not in cfg.devices:
        return None
    own = cfg.devices[dut].get("noise_nt")
    if own is None:
        return None
    ref = cfg.devices[reference].get("noise_nt") if reference in cfg.devices else None
    what = "and the reference's " if ref is not None else ""
    return even(math.hypot(float(own), float(ref or 0.0)),
                f"stated: the DUT's {what}noise_nt in {cfg.path} (none measured yet)")  # fmt: skip
