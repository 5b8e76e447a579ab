"""The chi-square and F tails without scipy.special, against scipy.special (gammaincc, betainc)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import betainc, fdtrc, gammaincc

from rig.calibration.stats import beta_i, chi2_sf, f_sf, gamma_q


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


@pytest.mark.parametrize("a", [0.5, 1.0, 6.5, 40.0, 87.0, 2500.0])
@pytest.mark.parametrize("b", [0.5, 2.0, 6.5, 44.0, 3000.0])
def test_beta_i_matches_scipy(a: float, b: float) -> None:
    mean = a / (a + b)
    for x in (1e-6, 0.3 * mean, 0.9 * mean, mean, min(1.1 * mean, 0.999), 0.5, 0.99, 1 - 1e-9):
        ours, ref = beta_i(a, b, x), float(betainc(a, b, x))
        assert abs(ours - ref) <= 1e-13 + 1e-10 * ref, (x, ours, ref)


@pytest.mark.parametrize(
    ("d1", "d2"), [(1, 1), (3, 10), (13, 80), (13, 171), (12.6, 83.4), (40, 4000)]
)
def test_f_sf_matches_scipy(d1: float, d2: float) -> None:
    for f in (0.0, 0.2, 0.8, 1.0, 1.3, 2.17, 3.0, 10.0, 100.0):
        ours, ref = f_sf(f, d1, d2), float(fdtrc(d1, d2, f))
        assert abs(ours - ref) <= 1e-13 + 1e-10 * ref, (f, ours, ref)


def test_beta_edges_and_errors() -> None:
    assert beta_i(2.0, 3.0, 0.0) == 0.0 and beta_i(2.0, 3.0, 1.0) == 1.0
    assert beta_i(1.0, 1.0, 0.37) == pytest.approx(0.37, rel=1e-14)  # the uniform distribution
    assert f_sf(-1.0, 3, 4) == 1.0
    for bad in [(0.0, 1.0, 0.5), (1.0, -1.0, 0.5), (1.0, 1.0, 1.5), (1.0, 1.0, float(np.nan))]:
        with pytest.raises(ValueError):
            beta_i(*bad)
