"""Report plots stay readable when a few samples are far out (rig.report.scaling; issue 30)."""

from __future__ import annotations

import numpy as np

from rig.report.scaling import robust_limits


def test_a_few_wild_samples_do_not_set_the_axis() -> None:
    rng = np.random.default_rng(1)
    residual_nt = 20.0 * rng.standard_normal(3000)
    residual_nt[[100, 101]] = [24_520.0, -23_000.0]  # two misdated samples
    limits = robust_limits(residual_nt)
    assert -200.0 < limits.lo < -60.0 and 60.0 < limits.hi < 200.0  # the bulk, not +-25 000
    assert limits.outside == 2
    assert limits.extreme == 24_520.0


def test_clean_data_are_all_shown() -> None:
    rng = np.random.default_rng(2)
    residual_nt = 20.0 * rng.standard_normal(3000)
    limits = robust_limits(residual_nt)
    assert limits.outside == 0
    assert limits.lo < residual_nt.min() and limits.hi > residual_nt.max()


def test_empty_and_constant() -> None:
    assert robust_limits([]).outside == 0
    flat = robust_limits(np.full(10, 5.0))
    assert flat.lo < 5.0 < flat.hi and flat.outside == 0


def test_a_logarithmic_axis_is_not_stretched_by_one_spike() -> None:
    """Issue 55: a live calibration's sigma spiked to 1e13 for one update and its panel spanned
    fifteen decades. The axis covers the bulk and the target; the spike is counted."""
    from rig.report.scaling import robust_log_limits

    sigma = np.geomspace(50.0, 5.0, 200)  # a filter's sigma converging, nT
    sigma[17] = 1e13
    limits = robust_log_limits(sigma, [2.0])  # the target below the bulk: taken in
    assert 1.0 < limits.lo < 2.0 and 50.0 < limits.hi < 500.0
    assert limits.outside == 1 and limits.extreme == 1e13
    assert robust_log_limits([]).lo == 0.1
