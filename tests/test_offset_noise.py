"""The offset noise model every characterization shares (issue 54), against noise generated
by bench/noise_draws.py, independently of the model and of the simulator's wander: white
noise, flicker shaped in the frequency domain and a random walk of Gaussian steps. Fixed seeds:
each test is deterministic (bench/bench_characterization_audit.py runs the 200-draw audits)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.noise_draws import offsets as draw
from rig.characterization.offset_noise import Bins, _flicker_bins, contiguous_bins
from rig.characterization.perming import offset_shifts
from rig.characterization.stability import allan_deviation, offset_drift

pytestmark = pytest.mark.montecarlo

RATE_HZ = 10.0


def test_the_generator_has_the_allan_variance_it_is_built_for() -> None:
    import allantools

    rng = np.random.default_rng(1)
    for mix, expect in (((1.0, 0.0, 0.0), 0.1 / 10.0), ((0.0, 1.0, 0.0), 1.0),
                        ((0.0, 0.0, 10.0), 100.0 / 3600.0 / 3.0 * 10.0)):  # fmt: skip
        got = [allantools.oadev(draw(rng, 20000, RATE_HZ, *mix), rate=RATE_HZ, data_type="freq",
                                taus=[10.0])[1][0] ** 2 for _ in range(20)]  # fmt: skip
        assert float(np.mean(got)) == pytest.approx(expect, rel=0.15), mix


def test_the_bins_covariance_is_the_sample_level_one_averaged() -> None:
    """White noise and a random walk exactly; flicker's Gauss-Markov sum against its own kernel
    summed over the samples."""
    t = np.arange(60) / 2.0
    bins, idx = contiguous_bins(t, 6)
    white, flicker, walk = bins.parts()
    avg = np.zeros((6, 60))
    for k, i in enumerate(idx):
        avg[k, i] = 1.0 / len(i)
    sample_walk = 3.0 * np.minimum.outer(t + 0.25, t + 0.25)  # the walk starts half a step early
    assert walk == pytest.approx(avg @ sample_walk @ avg.T, rel=0.02)
    assert white == pytest.approx(avg @ (2.0 * np.eye(60)) @ avg.T)
    sample_flicker = _flicker_bins(t, np.full(60, 0.5), 30.0)  # each reading its own bin
    assert flicker == pytest.approx(avg @ sample_flicker @ avg.T, rel=0.25)
    assert np.all(np.linalg.eigvalsh(white + flicker + walk) > 0)


@pytest.mark.parametrize("mix", [(1.0, 0.3, 5.0), (1.0, 0.1, 2.0), (0.5, 0.0, 5.0)])
def test_the_drift_sigma_covers_the_truth_under_mixed_noise(mix: tuple[float, ...]) -> None:
    """White, flicker and a random walk over 600 s: the random walk is no longer dropped when
    not shown at 2 sigma (the sigma came out 2-2.5 times too small: rms z 2.08 and 2.45 for the
    first two mixtures), and one REML puts at 0 still counts for what the record cannot rule
    out of it. 200 records of 3 axes (the audit bench): rms z 0.91 and 0.99, 96 % within 1.96
    sigma. Here 20 records of 3 axes."""
    rng = np.random.default_rng(7)
    drift_nt_per_h = 10.0
    t = np.arange(6000) / RATE_HZ
    z = []
    for _ in range(20):
        y = np.column_stack([draw(rng, len(t), RATE_HZ, *mix) for _ in range(3)])
        d = offset_drift(t, y + drift_nt_per_h * t[:, None] / 3600.0)
        z += list((np.asarray(d.per_12h_nt) - 12.0 * drift_nt_per_h) / np.asarray(d.sigma_nt))
        assert len(d.noise) == 3 and all(n.walk_nt2_per_s >= 0 for n in d.noise)
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.7 < rms < 1.3, (rms, np.round(z, 2))
    assert np.mean(np.abs(z) < 1.96) >= 0.88 and np.max(np.abs(z)) < 6.0, np.round(z, 2)


def test_a_random_walk_dominated_record_gives_intervals_not_a_traceback() -> None:
    """White 1 nT and a random walk of 5 nT/sqrt(h) for an hour at 1 Hz: the noise type found at
    long averaging times (alpha -4) crashed the interval routine in 9 of 20 records; now every
    record has its Allan deviation inside its interval, and a drift with a finite sigma."""
    t = np.arange(3600.0)
    for seed in range(20):
        rng = np.random.default_rng(seed)
        y = np.column_stack([draw(rng, len(t), 1.0, 1.0, 0.0, 5.0) for _ in range(3)])
        adev = allan_deviation(t, y)
        low, dev, high = (np.asarray(v) for v in (adev.low_nt, adev.adev_nt, adev.high_nt))
        assert np.all((low <= dev) & (dev <= high) & np.isfinite(high)), seed
        d = offset_drift(t, y)
        assert np.all(np.isfinite(d.sigma_nt)) and np.all(
            np.abs(d.per_12h_nt) < 5 * np.asarray(d.sigma_nt)
        )


def test_a_perming_shift_sigma_carries_the_walk_between_the_holds() -> None:
    """Two 60 s holds a minute apart, the offset wandering 20 nT/sqrt(h): the batch means of
    each hold alone gave rms z 2.85; fitted together with the noise, 0.93 over 70 draws."""
    rng = np.random.default_rng(5)
    hold, gap = 600, 600
    t = np.arange(2 * hold + gap) / RATE_HZ
    truth = np.array([3.0, 0.0, -2.0])
    z = []
    for _ in range(25):
        y = np.column_stack([draw(rng, len(t), RATE_HZ, 2.0, 0.0, 20.0) for _ in range(3)])
        y[hold + gap :] += truth
        before, after = slice(0, hold), slice(hold + gap, None)
        (shift,) = offset_shifts([t[before], t[after]], [y[before], y[after]])
        z += list((np.asarray(shift.shift_nt) - truth) / np.asarray(shift.sigma_nt))
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.7 < rms < 1.3 and np.mean(np.abs(z) < 1.96) >= 0.88, (rms, np.round(z, 2))


def test_too_few_bins_for_the_coefficients_is_a_clear_error() -> None:
    from rig.characterization.offset_noise import fit_bins

    bins = Bins(np.array([0.0, 1.0]), np.array([0.9, 1.9]), np.array([10.0, 10.0]), 10.0)
    with pytest.raises(ValueError, match="2 bins for 2 coefficients"):
        fit_bins(np.ones((2, 2)), np.zeros(2), bins)


def test_the_audit_bench_draws_every_scenario_and_runs_as_documented() -> None:
    """Each scenario of bench/bench_characterization_audit.py gives finite z values for one
    draw, and the command runs on Dask and prints its table (two draws)."""
    import subprocess
    import sys
    from pathlib import Path

    from bench.bench_characterization_audit import SCENARIOS

    for sc in SCENARIOS:
        if sc.name.startswith("thermal"):
            continue  # 6 h campaigns: the command below and the thermal tests cover them
        z, sigma = sc.draw(0)
        assert len(z) in (3, 9) and np.all(np.isfinite(z)) and np.all(np.asarray(sigma) > 0), (
            sc.name
        )
    bench = Path(__file__).resolve().parents[1] / "bench" / "bench_characterization_audit.py"
    out = subprocess.run([sys.executable, str(bench), "--draws", "2", "--workers", "1",
                          "--scenario", "perming, white 5"], capture_output=True, text=True,
                         timeout=300, check=True).stdout  # fmt: skip
    assert "perming, white 5 nT" in out and "scenarios off the goal" in out
