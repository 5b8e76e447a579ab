"""How far one run's reported sigma may fall from the prediction: a 68 % range per value.

The prediction is the typical run's sigma (issue 54: within +-20 % of the mean over runs, yet
only 50-65 % of single runs inside +-20 %). A run's statistical sigma scales with its own noise,
which moves between runs of one DUT (19-35 nT seen) and which the run estimates from its own
residuals (a chi-square with its degrees of freedom); the cage's terms do not move. So a single
run's combined sigma falls, 68 % of the time, within ``hypot(stat * f, sys)`` for ``f`` between
the two ends of:

* the noise's run-to-run spread: log-normal over the earlier runs whose noises the floor pools,
  one standard deviation widened to a prediction interval for a new run (Student's t at 84 % with
  n - 1 degrees of freedom, times sqrt(1 + 1/n)); per axis where the floor keeps each run's axes
  (``NoiseFloor.runs_axes_nt``), the widest of the three intervals (a value's sigma follows its
  axis's noise, which moves between runs more than the axes' rms: 30 runs of the shipped
  acceptance on the simulated cage, the vector fit's y and z values inside their range 7 % of the
  time from the rms alone), else over each run's rms (``NoiseFloor.runs_nt``); unknown with fewer
  than :data:`MIN_RUNS` runs (a floor given or stated, not measured);
* the run's own estimate of that noise: ``sqrt(chi2(q, nu) / nu)`` at q = 16 % and 84 %,
  ``nu`` the samples' residual degrees of freedom.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from rig.prediction.noise import NoiseFloor
from rig.prediction.predict import ParameterPrediction

MIN_RUNS = 3
"""Earlier runs needed for their spread to be estimated."""
LOW, HIGH = 0.16, 0.84


@dataclass(frozen=True)
class RunSpread:
    """The factors (ratio to the predicted noise) a single run's statistical sigma falls within,
    68 % of the time, and what they come from (one line)."""

    low: float
    high: float
    source: str

    def range_of(self, p: ParameterPrediction) -> tuple[float, float]:
        """The 68 % range of a single run's combined 1-sigma for value ``p`` (its unit)."""
        fixed = math.sqrt(max(p.combined**2 - p.statistical**2, 0.0))
        return (math.hypot(p.statistical * self.low, fixed),
                math.hypot(p.statistical * self.high, fixed))  # fmt: skip


def run_spread(noise: NoiseFloor, samples: int, parameters: int) -> RunSpread:
    """The spread for a fit of ``parameters`` values to ``samples`` three-axis samples under
    ``noise`` (see the module)."""
    from scipy import stats  # here, not at the top: scipy's import costs every CLI 0.8 s

    dof = max(3 * samples - parameters, 1)
    own_low = math.sqrt(stats.chi2.ppf(LOW, dof) / dof)
    own_high = math.sqrt(stats.chi2.ppf(HIGH, dof) / dof)
    axes = [a for i in range(3)
            if (a := noise_between_runs([run[i] for run in noise.runs_axes_nt])) is not None]  # fmt: skip
    per_axis = len(axes) == 3
    between = ((min(a[0] for a in axes), max(a[1] for a in axes)) if per_axis
               else noise_between_runs(noise.runs_nt))  # fmt: skip
    if between is None:
        return RunSpread(own_low, own_high, f"its own noise estimate ({dof} degrees of freedom);"
                         " how the noise moves between runs is not known (no earlier runs"
                         " pooled)")  # fmt: skip
    low, high = between
    return RunSpread(low * own_low, high * own_high,
                     f"the noise of {len(noise.runs_nt)} earlier runs ({min(noise.runs_nt):.1f}-"
                     f"{max(noise.runs_nt):.1f} nT{', per axis' if per_axis else ''}) and its own"
                     " estimate of it")  # fmt: skip


def noise_between_runs(runs_nt: Sequence[float]) -> tuple[float, float] | None:
    """The 68 % prediction interval of a new run's noise over the pooled floor (the runs' rms),
    as factors; None with fewer than :data:`MIN_RUNS` runs."""
    values = [v for v in runs_nt if v > 0]
    n = len(values)
    if n < MIN_RUNS:
        return None
    rms = math.sqrt(sum(v * v for v in values) / n)
    logs = [math.log(v / rms) for v in values]
    mean = sum(logs) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in logs) / (n - 1))
    from scipy import stats

    half = float(stats.t.ppf(HIGH, n - 1)) * sd * math.sqrt(1.0 + 1.0 / n)
    return math.exp(mean - half), math.exp(mean + half)
