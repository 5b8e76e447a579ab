"""The chi-square tail without scipy.special, against scipy.special.gammaincc."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import gammaincc

from rig.calibration.stats import chi2_sf, gamma_q


@pytest.mark.parametrize("dof", [1, 2, 3, 7, 24, 100, 1001, 99_976, 999_976, 9_999_976])
@pytest.mark.parametrize("ratio", [0.0, 0.3, 0.9, 0.99, 0.999, 1.0, 1.001, 1.01, 1.1, 1.5, 3.0])
def test_chi2_sf_matches_scipy(dof: int, ratio: float) -> None:
    stat = ratio * dof
    ours, ref = chi2_sf(stat, dof), float(gammaincc(dof / 2.0, stat / 2.0))
    assert abs(ours - ref) <= 1e-12 + 1e-9 * ref, (ours, ref)


@pytest.mark.parametrize("a", [0.5, 1.0, 4.5, 50.0, 5e4])
def test_far_upper_tail_keeps_relative_accuracy(a: float) -> None:
    for x in (a + 10 * math.sqrt(a) + 5, a + 30 * math.sqrt(a) + 20):
        ref = float(gammaincc(a, x))
        assert ref > 0.0
        assert gamma_q(a, x) == pytest.approx(ref, rel=1e-10)


def test_edges_and_errors() -> None:
    assert gamma_q(3.0, 0.0) == 1.0
    assert gamma_q(3.0, math.inf) == 0.0
    assert chi2_sf(2.0, 2) == pytest.approx(math.exp(-1.0), rel=1e-14)  # Q(1, x) = exp(-x)
    with pytest.raises(ValueError):
        gamma_q(0.0, 1.0)
    with pytest.raises(ValueError):
        gamma_q(1.0, -1.0)
    with pytest.raises(ValueError):
        gamma_q(1.0, float(np.nan))
