"""The prediction a run's own null hold updates (issue 55): a DUT unlike its history is seen at the
start of its run, not averaged away over the next dozen.

Before a run the noise floor comes from the newest runs of the same serial, else of the model (the
device), else the rig's stated noise (:mod:`rig.prediction.noise`). The run's ``null_field``
measures this unit's noise paired with the reference within seconds. When that differs from what
the history expects at null field by more than the history's own run-to-run spread allows (or by
more than 20 %, whichever is larger), the unit has changed or is another: the calibrate steps
still to come are predicted again on the noise the null hold measured (times the history's ratio
of sweep to null noise, where the history has both), and the run records both predictions with
the reason. When it agrees, the history's prediction stands and is recorded as confirmed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rig.config import RigConfig
from rig.prediction.noise import NoiseFloor, even, noise_floor, rest_floor
from rig.steps.null_field import NoiseFloorResult
from rig.steps.vocabulary import Procedure, RigTiming

MIN_CHANGE = 0.2
"""The smallest relative change of the null-field noise taken as a different DUT."""
SPREAD_SIGMAS = 3.0
"""A change must also exceed this many of the history's relative run-to-run spread."""


@dataclass(frozen=True)
class NullCheck:
    """This run's null-field noise (nT, paired with the reference) against the history's."""

    measured_nt: float
    expected_nt: float
    history: NoiseFloor
    threshold: float
    """The relative change (|measured/expected - 1|) beyond which the DUT counts as changed."""
    rest: NoiseFloor | None = None
    """The history's null-field noises (None: no earlier run measured one)."""

    @property
    def changed(self) -> bool:
        """The DUT is not the one its history describes."""
        return abs(self.measured_nt / self.expected_nt - 1.0) > self.threshold


def null_check(proc: Procedure, cfg: RigConfig | None, runs_dir: Path | None,
               this_run: Mapping[str, Any], null_name: str,
               exclude: str | None = None) -> NullCheck | None:  # fmt: skip
    """The null hold ``null_name`` of this run (its results ``this_run``) against the history
    (``runs_dir`` without run ``exclude``: this one); None without a paired noise."""
    value = this_run.get(null_name)
    found = NoiseFloorResult.from_dict(value) if isinstance(value, Mapping) else None
    measured = found.pair_noise_nt("dut") if found is not None else None
    if measured is None or not measured > 0:
        return None
    dut = proc.magnetometers.get("dut", "dut")
    serial = proc.parameters.get("dut_serial") or None
    history = noise_floor(proc, cfg, runs_dir, None, exclude=exclude)
    rest = rest_floor(runs_dir, dut, serial, exclude=exclude)
    expected = rest.pair_nt if rest is not None else history.pair_nt
    spread = _relative_spread(rest.runs_nt if rest is not None else ())
    return NullCheck(measured, expected, history, max(MIN_CHANGE, SPREAD_SIGMAS * spread), rest)


def _relative_spread(values: tuple[float, ...]) -> float:
    """The sample standard deviation over the mean of ``values`` (0 with fewer than 3)."""
    if len(values) < 3:
        return 0.0
    mean = sum(values) / len(values)
    var = sum((v - mean) ** 2 for v in values) / (len(values) - 1)
    return math.sqrt(var) / mean


def updated_floor(check: NullCheck) -> NoiseFloor:
    """The noise floor for the steps to come: the history's, or (changed) this run's null noise
    scaled by the history's ratio of sweep to null noise."""
    if not check.changed:
        return check.history
    rest = check.rest
    ratio = check.history.pair_nt / rest.pair_nt if rest is not None else 1.0
    return even(check.measured_nt * ratio,
                f"this run's null hold: {check.measured_nt:.1f} nT paired against"
                f" {check.expected_nt:.1f} nT its history expects"
                + (f", x{ratio:.2f} as that history's sweeps to its nulls" if rest is not None else ""))  # fmt: skip


def prediction_after_null(proc: Procedure, cfg: RigConfig | None, timing: RigTiming | None,
                          runs_dir: Path | None, this_run: Mapping[str, Any], null_name: str,
                          exclude: str | None = None) -> dict[str, Any] | None:  # fmt: skip
    """The record a run keeps after its null hold: the check, the noise used and every calibrate
    step's predicted combined 1-sigma by result path; None without a calibrate step or a paired
    noise."""
    from rig.prediction.procedure import predict_procedure

    if not any(s.kind == "calibrate" for s in proc.steps):
        return None
    check = null_check(proc, cfg, runs_dir, this_run, null_name, exclude)
    if check is None:
        return None
    floor = updated_floor(check)  # the history's runs read once, by null_check
    prediction = predict_procedure(proc, cfg, timing or RigTiming(), runs_dir, None, noise=floor,
                                   rest=check.rest)  # fmt: skip
    return {
        "null": null_name,
        "changed": check.changed,
        "null_noise_nt": check.measured_nt,
        "expected_null_noise_nt": check.expected_nt,
        "threshold": check.threshold,
        "history_noise_nt": check.history.pair_nt,
        "history_source": check.history.source,
        "noise_nt": floor.pair_nt,
        "noise_source": floor.source,
        "combined_sigma": {s.step: _by_path(s) for s in prediction.steps},
    }


def _by_path(step: Any) -> dict[str, float]:
    """A step prediction's combined 1-sigma by result path."""
    return {p.path: p.combined for p in step.parameters}


def summary_line(record: Mapping[str, Any]) -> str:
    """One line for the run's events and report."""
    head = (f"prediction after '{record['null']}': this DUT's noise at null field"
            f" {record['null_noise_nt']:.1f} nT")  # fmt: skip
    expected = (
        f"{record['expected_null_noise_nt']:.1f} nT expected (from {record['history_source']})"
    )
    if record["changed"]:
        return (f"{head} against {expected}, more than {100 * record['threshold']:.0f} % apart:"
                f" the calibrations are predicted again at {record['noise_nt']:.1f} nT, the"
                " sigmas they report scale with it")  # fmt: skip
    return (
        f"{head} agrees with the {expected}; the prediction at {record['noise_nt']:.1f} nT stands"
    )
