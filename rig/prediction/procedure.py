"""A whole procedure predicted: every calibrate step and every acceptance criterion that judges a
predicted value (``rig check --predict``)."""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rig.analysis import COVERAGE_K
from rig.cage.limits import CageLimits
from rig.cage_budget import cage_terms, certificate_of
from rig.calibration.budget import CageTerms
from rig.config import RigConfig
from rig.prediction.background import Background, background_field
from rig.prediction.duration import PredictedDuration, predicted_duration
from rig.prediction.live_calibrate_stop import LivePrediction, predict_live
from rig.prediction.noise import NoiseFloor, noise_floor, rest_floor
from rig.prediction.planned import dut_rate_hz, planned_data
from rig.prediction.predict import StepPrediction, pooled_steps, predict_step
from rig.steps.vocabulary import Procedure, RigTiming, Step


@dataclass(frozen=True)
class CriterionPrediction:
    """A criterion judged on the prediction: ``verdict`` is ``can pass``, ``CANNOT PASS`` or
    ``not predicted``; ``text`` says why, naming the limiting term."""

    name: str
    verdict: str
    text: str


@dataclass(frozen=True)
class ProcedurePrediction:
    """The noise floor used, each calibrate step's prediction and the criteria judged on them."""

    noise: NoiseFloor
    steps: tuple[StepPrediction, ...]
    criteria: tuple[CriterionPrediction, ...]
    duration: PredictedDuration
    live: tuple[LivePrediction, ...] = ()
    background: Background | None = None

    @property
    def cannot_pass(self) -> list[CriterionPrediction]:
        """The criteria this plan cannot pass whatever the DUT."""
        return [c for c in self.criteria if c.verdict == "CANNOT PASS"]


def predict_procedure(proc: Procedure, cfg: RigConfig | None, timing: RigTiming,
                      runs_dir: Path | None, noise_nt: float | None, seed: int = 0,
                      noise: NoiseFloor | None = None, rest: NoiseFloor | None = None,
                      background: Background | None = None) -> ProcedurePrediction:  # fmt: skip
    """Predict every calibrate step of ``proc`` on the rig ``cfg`` (None: no cage terms); the
    noise floor ``noise``, the rest floor ``rest`` (a live filter's noise) and the field at the
    cage's zero ``background`` when given, else found in ``runs_dir`` and ``cfg``
    (:mod:`rig.prediction.noise`, :mod:`rig.prediction.background`)."""
    if noise is None:
        noise = noise_floor(proc, cfg, runs_dir, noise_nt)
    dut = proc.magnetometers.get("dut", "dut")
    rate = dut_rate_hz(cfg, dut)
    cage = cage_terms_for(proc, cfg)
    rest = rest or rest_floor(runs_dir, dut, proc.parameters.get("dut_serial") or None)
    background = background or background_field(cfg, runs_dir, dut)
    live = tuple(predict_live(proc, s, timing, rate, rest.pair_nt if rest else noise.pair_nt, seed,
                              background, rest.runs_nt if rest else ())
                 for s in proc.steps if s.kind == "live_calibrate")  # fmt: skip
    scenarios = _live_stops(proc, live)

    def fit(step: Step) -> StepPrediction:
        # one prediction per distinct set of live stops (each earlier run's noise), pooled
        distinct = Counter(tuple(sorted(stops.items())) for stops in scenarios)
        preds = [(predict_step(step.name, step.params,
                               planned_data(proc, step, timing, rate, stops_s=dict(stops),
                                            background=background), noise, cage, seed), count)
                 for stops, count in distinct.items()]  # fmt: skip
        return pooled_steps(preds)

    steps = tuple(fit(s) for s in proc.steps if s.kind == "calibrate")
    criteria = [c for s in proc.steps if s.kind == "check" for c in s.params.get("criteria", [])]
    by_name = {p.step: p for p in steps}
    lives = {p.step: p for p in live}
    judged = tuple(judge_live(c, lives[c["result"]]) if c["result"] in lives else judge(c, by_name)
                   for c in criteria)  # fmt: skip
    duration = _duration(proc, cfg, timing)
    saved = tuple(sum(float(_step(proc, name).params["max_s"]) - dwell for name, dwell in stops.items())
                  for stops in scenarios if stops)  # fmt: skip
    return ProcedurePrediction(noise, steps, judged, dataclasses.replace(duration, saved_s=saved),
                               live, background)  # fmt: skip


def _step(proc: Procedure, name: str) -> Step:
    return next(s for s in proc.steps if s.name == name)


def _live_stops(proc: Procedure, live: tuple[LivePrediction, ...]) -> list[dict[str, float]]:
    """Per noise scenario (an earlier run's), where each live step that stops on its targets
    stops (s of its plan); one scenario without such steps."""
    early = [lp for lp in live if _stops_early(proc, lp) and lp.stops]
    count = max((len(lp.stops) for lp in early), default=1)
    return [{lp.step: lp.stops[min(i, len(lp.stops) - 1)].dwell_s for lp in early}
            for i in range(count)]  # fmt: skip


def _stops_early(proc: Procedure, live: LivePrediction) -> bool:
    """The live step stops on its targets (``stop_on_target: yes``)."""
    step = next(s for s in proc.steps if s.name == live.step)
    return str(step.params.get("stop_on_target", "yes")) == "yes"


def judge_live(criterion: dict[str, Any], live: LivePrediction) -> CriterionPrediction:
    """A criterion on a live step's ``live.sigma_at_stop.<group>`` against the predicted sigma of
    that group when the step stops (or at ``max_s`` when its targets are not met by then)."""
    name = str(criterion.get("name") or f"{criterion['result']}.{criterion['value']}")
    path, hi = str(criterion["value"]), criterion.get("max")
    group = path.removeprefix("live.sigma_at_stop.")
    if live.problem is not None:
        return CriterionPrediction(name, "CANNOT PASS", f"'{live.step}': {live.problem}")
    if path.startswith("springmann."):
        return CriterionPrediction(name, "can pass", "judged on the DUT's own value (a live result"
                                   " has no uncertainty budget, so no guard band)")  # fmt: skip
    if group == path or group not in live.sigmas or hi is None:
        return CriterionPrediction(name, "not predicted", f"'{path}' is not a predicted value")
    when = (f"when it stops after about {live.stop_s:.1f} s of dwell" if live.stop_s is not None
            else f"at its {live.max_s:g} s limit, '{live.limited_by}' not met")  # fmt: skip
    sigma = live.sigmas[group]
    verdict = "can pass" if sigma <= hi else "CANNOT PASS"
    return CriterionPrediction(name, verdict, f"predicted sigma {sigma:.3g} {when} (limit"
                               f" {hi:g}; {live.noise_nt:.1f} nT noise)")  # fmt: skip


def cage_limits(cfg: RigConfig | None) -> CageLimits | None:
    """The cage's limits the ramps keep to (None without a cage)."""
    if cfg is None or cfg.cage is None:
        return None
    c = cfg.cage
    return CageLimits(c.max_current_a, c.max_field_ut, c.max_slew_a_per_s, c.step_s, c.coil_tau_s)


def _duration(proc: Procedure, cfg: RigConfig | None, timing: RigTiming) -> PredictedDuration:
    """The procedure's time on the rig (ramps from the cage model in use)."""
    from rig.output_limits import cage_model

    limits = cage_limits(cfg)
    model = cage_model(cfg) if cfg is not None and limits is not None else None
    return predicted_duration(proc, model, limits, timing)


def cage_terms_for(proc: Procedure, cfg: RigConfig | None) -> CageTerms | None:
    """The cage's terms as the run will have them: the reference's certificate and place, the
    cage calibration record in use, the lab's gradient."""
    if cfg is None or cfg.cage is None:
        return None
    from rig.output_limits import cage_model

    model = cage_model(cfg)
    return cage_terms(certificate_of(cfg, proc.magnetometers.get("reference")),
                      model.to_dict() if model is not None else None,
                      cfg.cage.ambient_gradient_nt_per_m)  # fmt: skip


def judge(criterion: dict[str, Any], steps: dict[str, StepPrediction]) -> CriterionPrediction:
    """One criterion on the prediction: a ``sigma.*`` limit against the predicted statistical
    sigma; a limit on a calibrated value against the guard band ``2 x combined sigma`` the run
    will judge it with (both limits: the band must fit between them)."""
    name = str(criterion.get("name") or f"{criterion['result']}.{criterion['value']}")
    step = steps.get(str(criterion["result"]))
    if step is None:
        return CriterionPrediction(name, "not predicted", "not the result of a calibrate step")
    if step.problem is not None:
        return CriterionPrediction(name, "CANNOT PASS", f"'{step.step}' cannot be fitted:"
                                   f" {step.problem}")  # fmt: skip
    path = str(criterion["value"])
    lo, hi = criterion.get("min"), criterion.get("max")
    rows = step.by_path()
    if path.startswith("sigma.") and path.removeprefix("sigma.") in rows:
        row = rows[path.removeprefix("sigma.")]
        if hi is not None and row.statistical > hi:
            return CriterionPrediction(name, "CANNOT PASS", f"predicted sigma {row.statistical:.3g}"
                                       f" > limit {hi:g}; limited by {row.limited_by}")  # fmt: skip
        return CriterionPrediction(name, "can pass", f"predicted sigma {row.statistical:.3g}"
                                   f" (limit {hi}); limited by {row.limited_by}")  # fmt: skip
    if path not in rows:
        return CriterionPrediction(name, "not predicted", f"'{path}' is not a predicted value")
    row = rows[path]
    band = COVERAGE_K * row.combined
    if lo is not None and hi is not None and 2 * band >= hi - lo:
        return CriterionPrediction(name, "CANNOT PASS", f"the guard band +-{band:.3g} (2 x the"
                                   f" predicted combined sigma) does not fit within {lo:g}-{hi:g};"
                                   f" limited by {row.limited_by}")  # fmt: skip
    inside = " and ".join(x for x in (f">= {lo + band:.6g}" if lo is not None else "",
                                      f"<= {hi - band:.6g}" if hi is not None else "") if x)  # fmt: skip
    return CriterionPrediction(name, "can pass", f"passes when the DUT's value is {inside}"
                               f" (guard band +-{band:.3g}); limited by {row.limited_by}")  # fmt: skip
