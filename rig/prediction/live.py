"""When a live calibration will meet its targets, predicted from its plan.

A ``live_calibrate`` step runs a sequential filter on the scalar model with the noise it is given
(its ``noise_nt``, else the null field's noise of the DUT paired with the reference) and stops at
the first moment every target group's largest 1-sigma is met (after ``min_s``). A filter that has
converged holds the information of the samples it has seen, so its sigma at a time is the batch
scalar fit's on the samples up to then: the prediction fits the step's planned samples (its own
sphere fields and load profiles, settled as the step settles them) up to a time, and finds by
bisection the first time every target is met, or says which is not met by ``max_s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rig.calibration.fit import calibrate
from rig.calibration.residuals import Samples
from rig.calibration.result import CalibrationResult
from rig.calibration.targets import group_sigmas, unmet_targets
from rig.errors import CalibrationError
from rig.prediction.background import Background
from rig.prediction.planned import EARLY_REFERENCE_PERIODS, step_samples
from rig.prediction.predict import ParameterPrediction, flat_paths
from rig.procedure.plan import compile_step
from rig.steps.vocabulary import Procedure, RigTiming, Step

RESOLUTION_S = 0.5
"""The predicted stop time is found to within this (s)."""


@dataclass(frozen=True)
class LivePrediction:
    """A live step predicted: ``stop_s`` the time its targets are met (None: not by ``max_s``),
    the group sigmas then (or at ``max_s``) against the targets, and the last group met or the
    first unmet (``limited_by``)."""

    step: str
    noise_nt: float
    stop_s: float | None
    max_s: float
    sigmas: dict[str, float]
    targets: dict[str, float]
    limited_by: str
    problem: str | None = None
    parameters: tuple[ParameterPrediction, ...] = ()
    """Every reported value's sigma when the step stops (or at ``max_s``)."""
    samples: int = 0
    """The filter's updates by then (settled samples)."""


def predict_live(proc: Procedure, step: Step, timing: RigTiming, dut_rate_hz: float,
                 noise_nt: float, seed: int = 0,
                 background: Background | None = None) -> LivePrediction:  # fmt: skip
    """Predict live step ``step`` of ``proc`` (the filter's noise ``noise_nt`` unless the step
    gives its own; the field the cage leaves at zero, ``background``, on every set-point)."""
    p = step.params
    noise = float(p.get("noise_nt") or noise_nt)
    targets = {str(k): float(v) for k, v in dict(p.get("targets") or {}).items()}
    max_s, min_s = float(p["max_s"]), float(p["min_s"])
    channels = tuple(str(c) for c in p.get("telemetry") or ())
    plan = compile_step(step, proc.path.parent, timing)
    t, field, loads = step_samples(plan.commands, plan.duration_s, channels, dut_rate_hz,
                                   float(p["settle_s"]),
                                   EARLY_REFERENCE_PERIODS / timing.reference_rate_hz)  # fmt: skip
    if background is not None:
        field = field + background.for_step(proc, step)
    method = str(p.get("method") or "ukf")
    rng = np.random.default_rng([seed, len(t)])
    measured = field + 1e-3 * noise * rng.standard_normal(field.shape)

    def fit_at(until_s: float) -> _Fit | None:
        keep = t <= until_s
        if keep.sum() < 20:
            return None
        s = Samples.build(measured[keep], field_ut=field[keep], telemetry=loads[keep],
                          channels=channels)  # fmt: skip
        try:
            fit = calibrate(s, method, noise_nt=noise)
        except CalibrationError:
            return None
        return _Fit(group_sigmas(fit.sigma, fit.names), _parameters(fit, noise), int(keep.sum()))

    head = (step.name, noise)
    at_end = fit_at(max_s)
    if at_end is None:
        return LivePrediction(*head, None, max_s, {}, targets, "",
                              problem=f"too few samples in {max_s:g} s to fit")  # fmt: skip
    unmet = unmet_targets(at_end.sigmas, targets)
    if unmet:
        return LivePrediction(*head, None, max_s, at_end.sigmas, targets, unmet[0], None,
                              at_end.parameters, at_end.samples)  # fmt: skip
    lo, hi = min_s, max_s
    found = fit_at(lo)
    if found is None or unmet_targets(found.sigmas, targets):
        while hi - lo > RESOLUTION_S:
            mid = 0.5 * (lo + hi)
            got = fit_at(mid)
            if got is not None and not unmet_targets(got.sigmas, targets):
                hi = mid
            else:
                lo = mid
        found = fit_at(hi) or at_end
        lo = hi
    return LivePrediction(*head, lo, max_s, found.sigmas, targets, _last(found.sigmas, targets),
                          None, found.parameters, found.samples)  # fmt: skip


@dataclass(frozen=True)
class _Fit:
    sigmas: dict[str, float]
    parameters: tuple[ParameterPrediction, ...]
    samples: int


def _parameters(fit: CalibrationResult, noise_nt: float) -> tuple[ParameterPrediction, ...]:
    """Each reported value's sigma (the filter's own: a live result has no cage terms)."""
    sigma = fit.reported_sigma()
    why = f"noise ({noise_nt:.1f} nT, the filter's)"
    return tuple(ParameterPrediction(path, float(v), float(v), why)
                 for path, v in zip(flat_paths(fit.grouped(sigma)), sigma, strict=True))  # fmt: skip


def _last(sigmas: dict[str, float], targets: dict[str, float]) -> str:
    """The target group closest to its limit (the one that decides when the step stops)."""
    return max(targets, key=lambda k: sigmas.get(k, 0.0) / targets[k]) if targets else ""
