"""When a live calibration will meet its targets, predicted from its plan.

A ``live_calibrate`` step runs a sequential filter on the scalar model with the noise it is given
(its ``noise_nt``, else the null field's noise of the DUT paired with the reference) and stops at
the first moment every target group's largest 1-sigma is met (after ``min_s``). A filter that has
converged holds the information of the samples it has seen: the prediction runs the step's own
filter once over its planned samples (its sphere fields, on the field the cage leaves at zero,
and load profiles, settled as the step settles them), keeps each group's sigma every few updates
(:class:`rig.calibration.forecast.SigmaForecast`, which the run's live view also uses) and finds
the first update at which every target is met, or says which is not met by ``max_s``; the
values' sigmas then come from a fit of the samples up to that stop.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rig.calibration.estimate import delta_method
from rig.calibration.fit import calibrate
from rig.calibration.forecast import SigmaForecast
from rig.calibration.residuals import Samples, p_from_theta, parameter_names
from rig.calibration.sequential.realtime import FilterOptions, run_filter
from rig.calibration.targets import group_sigmas, unmet_targets
from rig.config import RigConfig
from rig.errors import CalibrationError
from rig.prediction.background import Background, background_field
from rig.prediction.planned import dut_rate_hz, step_samples
from rig.prediction.predict import ParameterPrediction, flat_paths
from rig.procedure.plan import compile_step, rig_timing
from rig.steps.vocabulary import Procedure, RigTiming, Step

PAIRING_PERIODS = 0.5
"""After a change has settled, a live step's first DUT sample waits this many reference periods on
average for a settled reference sample to pair with."""
FORECAST_ROWS = 100
"""Rows of a forecast (each converts the filter's covariance to the groups' sigmas: 12 ms)."""


@dataclass(frozen=True)
class LivePrediction:
    """A live step predicted: ``stop_s`` the time its targets are met (None: not by ``max_s``),
    the group sigmas then (or at ``max_s``) against the targets, and the last group met or the
    first unmet (``limited_by``). Over several noises (earlier runs'), the typical run: the mean
    stop and the rms of each sigma, each noise's stop in ``stops``."""

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
    forecast: SigmaForecast | None = None
    """The sigmas over the whole plan (the run's live forecast)."""
    stops: tuple[Stop, ...] = ()
    """Per noise the prediction was made for, where the step stops."""


@dataclass(frozen=True)
class Stop:
    """Where a live step stops at the filter noise ``noise_nt`` (nT): after ``updates`` settled
    samples at ``dwell_s`` into its plan (s; ``max_s`` when its targets are not met by then)."""

    noise_nt: float
    updates: int
    dwell_s: float
    met: bool


def predict_live(proc: Procedure, step: Step, timing: RigTiming, dut_rate_hz: float,
                 noise_nt: float, seed: int = 0, background: Background | None = None,
                 runs_nt: Sequence[float] = ()) -> LivePrediction:  # fmt: skip
    """Predict live step ``step`` of ``proc`` (the filter's noise ``noise_nt`` unless the step
    gives its own; the field the cage leaves at zero, ``background``, on every set-point). With
    ``runs_nt``, the noises earlier runs gave their filters (nT), the typical run over them: the
    stop moves with the noise (the sigmas scale with it), and what the step reports with where it
    stops (a stop before a load level leaves its coefficients far less known)."""
    p = step.params
    own = p.get("noise_nt")
    noise = float(own or noise_nt)
    noises = (noise,) if own or not runs_nt else tuple(float(v) for v in runs_nt)
    targets = {str(k): float(v) for k, v in dict(p.get("targets") or {}).items()}
    max_s, min_s = float(p["max_s"]), float(p["min_s"])
    method = str(p.get("method") or "ukf")
    t, s = planned_live(proc, step, timing, dut_rate_hz, noise, seed, background)
    head = (step.name, noise)
    try:
        forecast = filter_forecast(s, t, method, noise)
    except CalibrationError as exc:
        return LivePrediction(*head, None, max_s, {}, targets, "", problem=str(exc))
    first = int(np.sum(t < min_s)) + 1
    scaled = [forecast.scaled(q) for q in noises]
    stops = tuple(_stop(f, targets, first, t, min_s) for f in scaled)
    rows = [f.at(x.updates) for f, x in zip(scaled, stops, strict=True)]
    sigmas = {k: _rms([r[k] for r in rows]) for k in rows[0]}
    fits = {n: _parameters(s.head(n), method, noise) for n in sorted({x.updates for x in stops})}
    parameters = _pooled_parameters([(fits[x.updates], x.noise_nt / noise) for x in stops],
                                    _rms(list(noises)))  # fmt: skip
    n = round(float(np.mean([x.updates for x in stops])))
    if not all(x.met for x in stops):
        unmet = unmet_targets(sigmas, targets)
        return LivePrediction(*head, None, max_s, sigmas, targets, unmet[0] if unmet else "",
                              None, parameters, n, forecast, stops)  # fmt: skip
    stop_s = float(np.mean([x.dwell_s for x in stops]))
    return LivePrediction(*head, stop_s, max_s, sigmas, targets, _last(sigmas, targets), None,
                          parameters, n, forecast, stops)  # fmt: skip


def _stop(forecast: SigmaForecast, targets: dict[str, float], first: int, t_s: np.ndarray,
          min_s: float) -> Stop:  # fmt: skip
    """Where the step stops on ``forecast`` (its targets met from update ``first`` on)."""
    n = forecast.first_met(targets, from_updates=first)
    if n is None:
        return Stop(forecast.noise_nt, forecast.updates[-1], float(t_s[-1]), False)
    return Stop(forecast.noise_nt, n, max(min_s, float(t_s[n - 1])), True)


def _rms(values: Sequence[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def _pooled_parameters(scenarios: list[tuple[tuple[ParameterPrediction, ...], float]],
                       noise_nt: float) -> tuple[ParameterPrediction, ...]:  # fmt: skip
    """Each value's sigma over the scenarios (a fit's parameters, times its noise's ratio): the
    rms, as runs at those noises would report on average."""
    if not scenarios or any(not fit for fit, _ in scenarios):
        return ()
    first = scenarios[0][0]
    out = []
    for i, p in enumerate(first):
        v = _rms([fit[i].statistical * f for fit, f in scenarios])
        why = (f"noise ({noise_nt:.1f} nT rms over {len(scenarios)} runs' filters)"
               if len(scenarios) > 1 else p.limited_by)  # fmt: skip
        out.append(ParameterPrediction(p.path, v, v, why))
    return tuple(out)


def planned_live(proc: Procedure, step: Step, timing: RigTiming, dut_rate_hz: float,
                 noise_nt: float, seed: int = 0,
                 background: Background | None = None) -> tuple[np.ndarray, Samples]:  # fmt: skip
    """Live step ``step``'s planned samples (its sphere fields on ``background``, its load
    profiles, settled as the step settles them; the DUT reading the field with ``noise_nt`` nT)
    and their times in the plan (s)."""
    p = step.params
    channels = tuple(str(c) for c in p.get("telemetry") or ())
    plan = compile_step(step, proc.path.parent, timing)
    # the step's own rule (rig.steps.live_calibrate_run): a DUT sample counts from settle_s after a
    # change until the next one starts, once a settled reference sample has come to pair it with
    # (half a reference period later on average); no window before a change, as a batch fit has
    settle_s = float(p["settle_s"]) + PAIRING_PERIODS / timing.reference_rate_hz
    t, field, loads = step_samples(plan.commands, plan.duration_s, channels, dut_rate_hz,
                                   settle_s, 0.0)  # fmt: skip
    if background is not None:
        field = field + background.for_step(proc, step)
    rng = np.random.default_rng([seed, len(t)])
    measured = field + 1e-3 * noise_nt * rng.standard_normal(field.shape)
    return t, Samples.build(measured, field_ut=field, telemetry=loads, channels=channels)


def filter_forecast(s: Samples, t_s: np.ndarray, method: str, noise_nt: float) -> SigmaForecast:
    """The filter ``method`` run once over ``s`` (dated ``t_s``, s): each target group's sigma
    after every few updates (the live step evaluates the same covariance as it runs)."""
    _, history = run_filter(
        s, FilterOptions(method=method), 1e-3 * noise_nt, history_rows=FORECAST_ROWS
    )
    names = parameter_names(s.channels, vector=False)
    updates, dwell, rows = [], [], []
    for k, theta, cov in zip(history.index, history.theta, history.covariance, strict=True):
        try:
            _, cov_p = delta_method(p_from_theta, theta, cov, method)
        except CalibrationError:
            continue  # not an ellipsoid yet
        updates.append(int(k) + 1)
        dwell.append(float(t_s[k]))
        rows.append(group_sigmas(np.sqrt(np.clip(np.diag(cov_p), 0.0, None)), names))
    if not rows:
        raise CalibrationError("the filter never became observable on the planned samples")
    sigmas = {g: tuple(r[g] for r in rows) for g in rows[-1]}
    return SigmaForecast(tuple(updates), tuple(dwell), sigmas, noise_nt)


def _parameters(s: Samples, method: str, noise_nt: float) -> tuple[ParameterPrediction, ...]:
    """Each reported value's sigma on ``s`` (the filter's own: a live result has no cage
    terms); none when those samples cannot be fitted."""
    try:
        fit = calibrate(s, method, noise_nt=noise_nt)
    except CalibrationError:
        return ()
    sigma = fit.reported_sigma()
    why = f"noise ({noise_nt:.1f} nT, the filter's)"
    return tuple(ParameterPrediction(path, float(v), float(v), why)
                 for path, v in zip(flat_paths(fit.grouped(sigma)), sigma, strict=True))  # fmt: skip


def _last(sigmas: dict[str, float], targets: dict[str, float]) -> str:
    """The target group closest to its limit (the one that decides when the step stops)."""
    return max(targets, key=lambda k: sigmas.get(k, 0.0) / targets[k]) if targets else ""


def live_forecast(proc: Procedure, step: Step, cfg: RigConfig, runs_dir: Path | None,
                  noise_nt: float, this_run: Mapping[str, Any]) -> SigmaForecast | None:  # fmt: skip
    """What a run shows beside a live step's sigmas: the step's plan forecast on rig ``cfg`` at
    the filter's noise ``noise_nt`` (the field the cage leaves at zero from the run's own results
    ``this_run``, else ``runs_dir``'s runs); None when the plan cannot be fitted."""
    dut = proc.magnetometers.get("dut", "dut")
    noise = float(step.params.get("noise_nt") or noise_nt)
    t, s = planned_live(proc, step, rig_timing(cfg) or RigTiming(), dut_rate_hz(cfg, dut), noise,
                        background=background_field(cfg, runs_dir, dut, this_run))  # fmt: skip
    try:
        return filter_forecast(s, t, str(step.params.get("method") or "ukf"), noise)
    except CalibrationError:
        return None
