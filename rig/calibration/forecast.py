"""A live calibration's sigmas forecast over its samples, and when its targets will be met.

The forecast is the step's own sequential filter run over the samples its plan will give it
(:mod:`rig.prediction.live_calibrate_stop`): each target group's 1-sigma after so many filter updates. During
the run the filter's sigmas are compared with the forecast at the same number of updates; their
ratio (how much noisier or quieter this run is than planned, per group) carries the rest of the
forecast forward, and the first update count at which every scaled group meets its target is the
predicted stop. Counting updates, not seconds, leaves out what the plan cannot know (ramps,
samples left out while settling); the run's own rate of updates turns the count into seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.calibration.targets import unmet_targets


@dataclass(frozen=True)
class SigmaForecast:
    """Per target group the filter's 1-sigma (the target's unit) after ``updates[i]`` updates,
    ``dwell_s[i]`` s into the step's plan, with ``noise_nt`` of noise."""

    updates: tuple[int, ...]
    dwell_s: tuple[float, ...]
    sigmas: dict[str, tuple[float, ...]]
    noise_nt: float

    def scaled(self, noise_nt: float) -> SigmaForecast:
        """The same plan with another noise (nT): every sigma in proportion (the filter's
        covariance once the data outweigh its start)."""
        f = noise_nt / self.noise_nt
        return SigmaForecast(self.updates, self.dwell_s,
                             {k: tuple(f * v for v in vs) for k, vs in self.sigmas.items()},
                             noise_nt)  # fmt: skip

    def at(self, updates: int) -> dict[str, float]:
        """Each group's sigma after ``updates`` updates: interpolated in log-log between the
        rows; beyond the last row falling as 1/sqrt(updates), before the first the first row's."""
        n = np.asarray(self.updates, float)
        x = math.log(max(updates, 1))
        out = {}
        for k, vs in self.sigmas.items():
            logs = np.log(np.maximum(np.asarray(vs, float), 1e-300))
            if updates > n[-1]:
                out[k] = float(vs[-1]) * math.sqrt(n[-1] / updates)
            else:
                out[k] = float(np.exp(np.interp(x, np.log(n), logs)))
        return out

    def first_met(self, targets: dict[str, float], ratios: dict[str, float] | None = None,
                  from_updates: int = 0) -> int | None:  # fmt: skip
        """The first row's update count (not before ``from_updates``) at which every group's
        sigma, times its ``ratio`` (1 when not given), meets its target; None if no row does."""
        r = ratios or {}
        for i, n in enumerate(self.updates):
            if n < from_updates:
                continue
            now = {k: r.get(k, 1.0) * vs[i] for k, vs in self.sigmas.items()}
            if not unmet_targets(now, targets):
                return n
        return None

    def dwell_at(self, updates: int) -> float:
        """The plan's dwell time (s) by which the filter has had ``updates`` updates."""
        return float(np.interp(updates, self.updates, self.dwell_s))


@dataclass(frozen=True)
class StopForecast:
    """During a run: the update count at which the targets are predicted met (None: not by
    the plan's end), the seconds until then at the run's rate, and the ratios used."""

    updates: int | None
    eta_s: float | None
    ratios: dict[str, float]
    limiting: str
    planned: dict[str, float]
    """The forecast's own sigma of each group at the run's update count."""

    def line(self) -> str:
        """For the live view."""
        if self.updates is None:
            return f"forecast: '{self.limiting}' not met by max_s at this run's noise"
        return f"forecast: targets met in about {self.eta_s:.0f} s ({self.updates} updates)"


def forecast_stop(forecast: SigmaForecast, sigmas: dict[str, float], updates: int,
                  elapsed_s: float, targets: dict[str, float]) -> StopForecast:  # fmt: skip
    """Where a run's filter (``sigmas`` after ``updates`` updates, ``elapsed_s`` s into the
    step) will meet ``targets``, carried forward from ``forecast``."""
    planned = forecast.at(updates)
    ratios = {k: sigmas[k] / planned[k] for k in planned if k in sigmas and planned[k] > 0}
    n = forecast.first_met(targets, ratios, updates)
    if n is None and not unmet_targets({k: ratios.get(k, 1.0) * v for k, v in planned.items()},
                                       targets):  # fmt: skip
        n = updates  # met now (between two rows)
    rate = updates / elapsed_s if elapsed_s > 0 and updates > 0 else 0.0
    eta = None if n is None or rate <= 0 else (n - updates) / rate
    scaled_end = {k: ratios.get(k, 1.0) * vs[-1] for k, vs in forecast.sigmas.items()}
    worst = max(targets, key=lambda k: scaled_end.get(k, math.inf) / targets[k]) if targets else ""
    return StopForecast(n, eta, ratios, worst, planned)
