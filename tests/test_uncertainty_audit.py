"""The promise of ADR 0025 by Monte Carlo: with white or coloured (AR(1)) noise, the vector fit's
offsets and scales come out with rms (error / reported sigma) between 0.8 and 1.25 over 200 draws
(bench/bench_uncertainty_audit.py prints every parameter and more scenarios)."""

from __future__ import annotations

import numpy as np
import pytest

from rig.calibration.audit import SCENARIOS, audit, summary

CHECKED = ("a", "b", "c", "x0", "y0", "z0")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["white", "AR(1) tau 1", "AR(1) tau 3", "AR(1) tau 10"])
def test_offsets_and_scales_have_honest_sigmas(name: str) -> None:
    scenario = next(sc for sc in SCENARIOS if sc.name == name)
    names, z = audit(scenario, 200)
    rms = summary(z)[0]
    idx = [names.index(k) for k in CHECKED]
    assert np.all((rms[idx] >= 0.8) & (rms[idx] <= 1.25)), dict(
        zip(CHECKED, rms[idx].round(2), strict=True)
    )
