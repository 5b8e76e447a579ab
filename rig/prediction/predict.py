"""The sigma each ``calibrate`` step will report, predicted from its plan (before any current).

For each calibrate step: the samples the plan gives it (:mod:`rig.prediction.planned`), a DUT
whose readings are the planned field plus the noise floor (:mod:`rig.prediction.noise`: the DUT
less the reference, per axis), fitted by the step's own estimator - so the sigma is the one the
run will report, computed the way the run computes it (residual variance, per-axis covariance,
the same parameters) - and the cage's terms propagated through the same fit as the run's
uncertainty budget does (ADR 0028). One seeded draw of the noise: the sigma of a fit to several
hundred samples varies by a few percent between draws, as it does between runs. What the
prediction leaves out is said with it: drift of the DUT over the run, temperature, correlated
residuals (the run inflates its sigma for them; the simulated cage shows none).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from rig.calibration.budget import CageTerms, UncertaintyBudget, corrected, propagate
from rig.calibration.estimators import DEFAULT_METHOD
from rig.calibration.fit import calibrate
from rig.calibration.residuals import Samples
from rig.calibration.result import CalibrationResult
from rig.errors import CalibrationError
from rig.prediction.noise import NoiseFloor
from rig.prediction.planned import PlannedData

REFERENCE_JITTER_NT = 1.0
"""The reference's readings are never exactly the set field (a null field reads a few nT): the
planned field gets this much noise (nT per axis; the noise floor carries the reference's own)."""
BUDGET_ROWS = 4000
"""The cage terms' sensitivities are found on at most about this many evenly spread samples (a
term moves the estimate by the same amount on fewer samples; the statistical sigma uses all)."""
MIN_SAMPLES = 20
AXES = "xyz"


@dataclass(frozen=True)
class ParameterPrediction:
    """One reported value: its result path (``springmann.a``, ``k_ut_per_unit.load_bus[x]``),
    its predicted statistical and combined 1-sigma (the value's unit) and what limits it."""

    path: str
    statistical: float
    combined: float
    limited_by: str


@dataclass(frozen=True)
class StepPrediction:
    """What a calibrate step will report, predicted: ``parameters`` (empty when it cannot be
    fitted, ``problem`` then says why), the samples and the steps they come from."""

    step: str
    method: str
    samples: int
    seconds: float
    steps: tuple[str, ...]
    parameters: tuple[ParameterPrediction, ...]
    left_out: tuple[str, ...] = ()
    problem: str | None = None

    def by_path(self) -> dict[str, ParameterPrediction]:
        """The parameters by result path."""
        return {p.path: p for p in self.parameters}


def predict_step(name: str, params: dict[str, Any], planned: PlannedData, noise: NoiseFloor,
                 cage: CageTerms | None, seed: int = 0) -> StepPrediction:  # fmt: skip
    """Predict calibrate step ``name`` (its ``params``) on ``planned`` samples."""
    scalar = params.get("model") == "scalar"
    method = str(params.get("method") or DEFAULT_METHOD["scalar" if scalar else "vector"])
    head = (name, method, planned.n, planned.seconds, planned.steps)
    if planned.n < MIN_SAMPLES:
        return StepPrediction(*head, (), problem=f"{planned.n} samples would be kept from"
                              f" {', '.join(planned.steps) or 'no step'}: too few to fit")  # fmt: skip
    rng = np.random.default_rng([seed, planned.n])
    noise_ut = 1e-3 * np.asarray(noise.axes_nt) * rng.standard_normal(planned.field_ut.shape)
    field_ut = planned.field_ut + 1e-3 * REFERENCE_JITTER_NT * rng.standard_normal(noise_ut.shape)
    samples = Samples.build(planned.field_ut + noise_ut, field_ut=field_ut,
                            telemetry=planned.telemetry, channels=planned.channels)  # fmt: skip
    samples = corrected(samples, cage.correction if cage is not None else None)

    def refit(s: Samples) -> CalibrationResult:
        return calibrate(s, method, noise_nt=params.get("noise_nt") or None)

    try:
        fit = refit(samples)
        budget = _budget(samples, refit, fit, cage)
    except CalibrationError as exc:
        return StepPrediction(*head, (), problem=str(exc))
    rows = _parameters(fit, budget, noise, planned.n)
    return StepPrediction(*head, rows, budget.left_out)


def pooled_steps(preds: list[tuple[StepPrediction, int]]) -> StepPrediction:
    """One step predicted for several scenarios (each with its count of runs): every sigma the
    rms over the runs, the samples their mean, the limiting term the most common scenario's."""
    if len(preds) == 1:
        return preds[0][0]
    preds = sorted(preds, key=lambda pc: -pc[1])
    first = preds[0][0]
    weights = np.array([c for _, c in preds], float) / sum(c for _, c in preds)
    if any(p.problem is not None or not p.parameters for p, _ in preds):
        return next(p for p, _ in preds if p.problem is not None or not p.parameters)

    def rms(values: list[float]) -> float:
        return float(np.sqrt(np.sum(weights * np.square(values))))

    rows = tuple(ParameterPrediction(q.path, rms([p.parameters[i].statistical for p, _ in preds]),
                                     rms([p.parameters[i].combined for p, _ in preds]),
                                     q.limited_by)
                 for i, q in enumerate(first.parameters))  # fmt: skip
    samples = round(float(np.sum(weights * [p.samples for p, _ in preds])))
    seconds = float(np.sum(weights * [p.seconds for p, _ in preds]))
    return StepPrediction(first.step, first.method, samples, seconds, first.steps, rows,
                          first.left_out)  # fmt: skip


def _budget(samples: Samples, refit: Any, fit: CalibrationResult,
            cage: CageTerms | None) -> UncertaintyBudget:  # fmt: skip
    """The cage terms' contributions, found on at most about :data:`BUDGET_ROWS` samples."""
    terms = cage.terms if cage is not None else ()
    left = cage.left_out if cage is not None else ("the cage's terms: no rig configuration",)
    if not terms:
        return UncertaintyBudget(fit.reported_sigma(), (), tuple(left))
    step = max(1, samples.n // BUDGET_ROWS)
    few = samples.rows(slice(0, None, step)) if step > 1 else samples
    values = refit(few).reported() if step > 1 else fit.reported()
    moved = propagate(few, lambda s: refit(s).reported(), values, fit.reported_sigma(), terms,
                      left)  # fmt: skip
    return moved


def _parameters(fit: CalibrationResult, budget: UncertaintyBudget, noise: NoiseFloor,
                n: int) -> tuple[ParameterPrediction, ...]:  # fmt: skip
    """Per reported value: statistical, combined, and the largest contributor's name."""
    statistical = budget.statistical
    combined = budget.combined_sigma
    paths = flat_paths(fit.grouped(statistical))
    rows = []
    for i, path in enumerate(paths):
        biggest, why = abs(statistical[i]), f"noise ({noise.pair_nt:.1f} nT over {n} samples)"
        for term in budget.terms:
            if abs(term.contribution[i]) > biggest:
                biggest, why = abs(term.contribution[i]), f"{term.group}: {term.name}"
        rows.append(ParameterPrediction(path, float(statistical[i]), float(combined[i]), why))
    return tuple(rows)


def flat_paths(grouped: dict[str, Any], prefix: str = "") -> list[str]:
    """The result paths of a grouped block in :meth:`CalibrationResult.reported` order; a list's
    elements as ``name[x]`` (axes) or ``name[i]``."""
    out = []
    for key, value in grouped.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict):
            out += flat_paths(value, f"{path}.")
        elif isinstance(value, list):
            out += [f"{path}[{AXES[i] if len(value) == 3 else i}]" for i in range(len(value))]
        else:
            out.append(path)
    return out
