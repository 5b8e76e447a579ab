"""Telemetry delays recovered from synthetic truth: within 3 sigma, sigma matching the spread over
Monte Carlo runs, and the Cramer-Rao bound equal to sigma when the noise is known."""

from __future__ import annotations

import numpy as np
import pytest

from rig.calibration.estimators import FitRequest, estimator
from rig.calibration.profiled import ProfileFit, delay_parameter, profile_fit
from rig.calibration.residuals import Samples
from rig.calibration.synthetic import DELAY_K_UT_PER_A, delayed_currents
from rig.errors import CalibrationError

pytestmark = pytest.mark.montecarlo

TRUE_DELAYS_S = (0.35, -0.12)
K_TRUE = DELAY_K_UT_PER_A  # uT per A
NOISE_UT = 0.05


def cage_with_delayed_currents(seed: int, n: int = 3000, rate_hz: float = 20.0):
    """A cage run at ``rate_hz``: the field steps through directions, two harness currents vary
    smoothly (sinusoids and a ramp), and their bias reaches the DUT ``TRUE_DELAYS_S`` late."""
    case = delayed_currents(n, seed=seed, rate_hz=rate_hz, noise_ut=NOISE_UT,
                            delays_s=TRUE_DELAYS_S)  # fmt: skip
    return case.samples, case.time_s


def estimate_delays(s, t, channels, refit, max_delay_s=2.0, noise_ut=None) -> ProfileFit:
    """The delays of ``channels`` as ``rig calibrate --delay`` finds them."""
    params = tuple(delay_parameter(s, t, c, max_delay_s) for c in channels)
    return profile_fit(s, params, refit, noise_ut=noise_ut)


def _vector_refit(data: Samples):
    return estimator("vector").run(data, FitRequest("vector", NOISE_UT, None, None, None, None))


def test_delays_recovered_within_three_sigma_with_the_crlb() -> None:
    s, t = cage_with_delayed_currents(1)
    fit = estimate_delays(s, t, ("i_a", "i_b"), _vector_refit, max_delay_s=1.0, noise_ut=NOISE_UT)
    err = fit.values - np.array(TRUE_DELAYS_S)
    assert np.all(np.abs(err) < 3 * fit.sigma), (fit.values, fit.sigma)
    assert np.all(fit.sigma < 0.01)  # ms-level on 3000 samples of smooth currents
    np.testing.assert_allclose(fit.crlb_sigma, fit.sigma, rtol=0.1)  # noise known and right
    k = fit.estimate.p[12:].reshape(-1, 3)
    np.testing.assert_allclose(k, K_TRUE, atol=0.01)


def test_the_other_parameters_carry_the_delays_uncertainty() -> None:
    """A refit at the found delays gives the others' covariance with the delays held; the result
    adds what the delays' own uncertainty moves them by (``C + G S G^T``). With the delays'
    white-noise sigma that is exactly the whole model's covariance block, assembled here from
    the Jacobian with the delay columns appended and inverted whole."""
    from dataclasses import replace

    from rig.calibration.profiled import weighted_residuals

    s, t = cage_with_delayed_currents(2, n=1500)
    fit = estimate_delays(s, t, ("i_a", "i_b"), _vector_refit, max_delay_s=1.0)
    est = fit.estimate
    r, jac_p = weighted_residuals(est, fit.samples)
    cols = []
    for j, prm in enumerate(fit.params):
        shifted = []
        for sign in (1.0, -1.0):
            trial = fit.values.copy()
            trial[j] += sign * prm.step
            data = s
            for q, v in zip(fit.params, trial, strict=True):
                data = q.apply(data, float(v))
            shifted.append(weighted_residuals(est, data)[0])
        cols.append((shifted[0] - shifted[1]) / (2.0 * prm.step))
    jac = np.column_stack([jac_p, *cols])
    variance = float(r @ r) / (r.size - jac.shape[1])
    whole = variance * np.linalg.inv(jac.T @ jac)
    k = jac_p.shape[1]
    held = variance * np.linalg.inv(jac_p.T @ jac_p)
    white = replace(fit, coupled_sigma=np.sqrt(np.diag(whole)[k:]), others_covariance=None)
    np.testing.assert_allclose(white.marginal_covariance(held), whole[:k, :k],
                               rtol=1e-6, atol=1e-9 * float(np.max(np.abs(whole[:k, :k]))))  # fmt: skip
    assert np.all(np.diag(whole[:k, :k]) >= np.diag(held) * (1.0 - 1e-9))
    # with white residuals the result takes the whole model's sandwich of each sample's score
    inv = np.linalg.inv(jac.T @ jac)
    scores = np.einsum("nap,na->np", jac.reshape(s.n, 3, -1), r.reshape(s.n, 3))
    sandwich = inv @ scores.T @ scores @ inv
    assert fit.others_covariance is not None
    np.testing.assert_allclose(fit.marginal_covariance(held), sandwich[:k, :k], rtol=1e-6,
                               atol=1e-9 * float(np.max(np.abs(sandwich[:k, :k]))))  # fmt: skip


def test_delay_sigma_matches_the_monte_carlo_spread() -> None:
    errs, sigmas = [], []
    runs = 15
    for seed in range(runs):
        s, t = cage_with_delayed_currents(100 + seed, n=1200)
        fit = estimate_delays(s, t, ("i_a", "i_b"), _vector_refit, max_delay_s=1.0)
        errs.append(fit.values - np.array(TRUE_DELAYS_S))
        sigmas.append(fit.sigma)
    spread = np.std(errs, axis=0, ddof=1)
    mean_sigma = np.mean(sigmas, axis=0)
    assert np.all(np.abs(np.mean(errs, axis=0)) < 3 * mean_sigma / np.sqrt(runs))  # unbiased
    assert np.all((spread > 0.6 * mean_sigma) & (spread < 1.5 * mean_sigma)), (spread, mean_sigma)


def test_a_channel_that_never_changes_has_no_delay_to_find() -> None:
    s, t = cage_with_delayed_currents(2, n=600)
    flat = Samples(s.measured_ut, s.field_magnitude_ut, np.column_stack([s.telemetry[:, 0],
                   np.ones(s.n)]), s.channels, s.field_ut)  # fmt: skip
    with pytest.raises(CalibrationError, match="never changes"):
        estimate_delays(flat, t, ("i_b",), _vector_refit)
    with pytest.raises(CalibrationError, match="increasing"):
        estimate_delays(s, t[::-1], ("i_a",), _vector_refit)
    with pytest.raises(CalibrationError, match="not a --telemetry channel"):
        estimate_delays(s, t, ("i_c",), _vector_refit)


def _csv(tmp_path, s: Samples, t: np.ndarray):
    rows = np.column_stack([t, s.measured_ut, s.field_ut, np.linalg.norm(s.field_ut, axis=1),
                            s.telemetry])  # fmt: skip
    path = tmp_path / "run.csv"
    np.savetxt(path, rows, delimiter=",", header="t_s,mx,my,mz,hx,hy,hz,h,i_a,i_b", comments="",
               fmt="%.6f")  # fmt: skip
    return path


def test_rig_calibrate_delay_vector_and_scalar(
    tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The command: the delays in the table and in the result file, with sigma and CRLB; a scalar
    (ML) fit of the same file finds them too, less sharply."""
    import json

    from rig.cli import main

    s, t = cage_with_delayed_currents(3)
    path = _csv(tmp_path, s, t)
    base = [str(path), "--measured", "mx,my,mz", "--telemetry", "i_a,i_b", "--time", "t_s",
            "--delay", "i_a,i_b", "--max-delay-s", "1", "--noise-nt", "50"]  # fmt: skip
    for ref, out in ((["--field", "hx,hy,hz"], "v.json"), (["--field-magnitude", "h"], "s.json")):
        assert main(["calibrate", *base, *ref, "--out", str(tmp_path / out)]) == 0
        text = capsys.readouterr().out
        assert "delay[i_a]" in text and "delay[i_b]" in text
        doc = json.loads((tmp_path / out).read_text())
        for j, ch in enumerate(("i_a", "i_b")):
            tau, sig = doc["delay_s"][ch], doc["sigma"]["delay_s"][ch]
            assert abs(tau - TRUE_DELAYS_S[j]) < 3 * sig, (out, ch, tau, sig)
            assert doc["crlb_sigma"]["delay_s"][ch] > 0


def test_rig_calibrate_delay_needs_times_and_a_batch_method(
    tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    from rig.cli import main

    s, t = cage_with_delayed_currents(4, n=600)
    path = _csv(tmp_path, s, t)
    base = [str(path), "--measured", "mx,my,mz", "--telemetry", "i_a,i_b", "--delay", "i_a"]
    assert main(["calibrate", *base, "--field", "hx,hy,hz"]) == 2
    assert "--delay needs the sample times: add --time COL" in capsys.readouterr().err
    filt = ["--time", "t_s", "--method", "ukf", "--noise-nt", "50", "--field-magnitude", "h"]
    assert main(["calibrate", *base, *filt]) == 2
    assert "need a batch method" in capsys.readouterr().err


def commanded_staircase_run(seed: int, delay_s: float, n: int = 2400):
    """A tracked run as the rig records it: a current commanded every 50 ms along a smooth path
    (a staircase: each value holds until the next command), the DUT sampling at 20.3 Hz, the bias reaching it ``delay_s`` late, and the telemetry column the held value at each
    DUT time. Returns (samples, DUT times, command times, commanded values)."""
    rng = np.random.default_rng(seed)
    t_cmd = np.arange(n) * 0.05
    i_cmd = np.round(
        1.0 + np.sin(2 * np.pi * t_cmd / 3.1) + 0.4 * np.sin(2 * np.pi * t_cmd / 0.9), 3
    )
    # the DUT's clock is not the rig's: its samples drift through the command phase (at the same
    # rate and phase every sample would see the same part of each step, and a delay would only be
    # known to within one command interval)
    t = np.arange(n) / 20.3 + 0.05 * rng.uniform(0.0, 1.0)

    def held(times: np.ndarray) -> np.ndarray:
        return i_cmd[np.clip(np.searchsorted(t_cmd, times, side="right") - 1, 0, None)]

    dirs = rng.standard_normal((n // 50 + 1, 3))
    h = np.repeat(40.0 * dirs / np.linalg.norm(dirs, axis=1)[:, None], 50, axis=0)[:n]
    k = np.array([0.9, -0.6, 1.1])
    m = h + np.array([3.0, -2.0, 5.0]) + np.outer(held(t - delay_s), k)
    m += NOISE_UT * rng.standard_normal((n, 3))
    s = Samples.build(m, field_ut=h, telemetry=held(t)[:, None], channels=("i",))
    return s, t, t_cmd, i_cmd


@pytest.mark.parametrize("truth_s", [0.025, 0.05, 0.08])
def test_a_commanded_staircase_gives_the_delay_within_three_sigma(truth_s: float) -> None:
    """The command log as a staircase with centred ramps (how rig calibrate RUN --delay reads a
    run) recovers a delay of half, one and 1.6 command intervals within 3 sigma in each of three
    runs, at the sub-millisecond sigma the steps allow."""
    from rig.analysis import staircase_series

    for seed in range(3):
        s, t, t_cmd, i_cmd = commanded_staircase_run(seed, truth_s)
        series = staircase_series(t_cmd, i_cmd, 0.1)
        fit = profile_fit(s, (delay_parameter(s, t, "i", 0.5, series),), _vector_refit,
                          noise_ut=NOISE_UT)  # fmt: skip
        assert abs(fit.values[0] - truth_s) < 3 * fit.sigma[0], (seed, fit.values, fit.sigma)
        assert fit.sigma[0] < 0.002


def test_phase_lock_is_told_from_a_drifting_clock() -> None:
    """DUT samples at the commands' 20 Hz, jittered by 2 ms: locked, interval 50 ms; at 20.3 Hz
    they drift through every phase of the commands: not locked."""
    from rig.analysis import phase_locked_interval_s

    rng = np.random.default_rng(5)
    t_cmd = np.arange(1200) * 0.05
    commands = np.column_stack([t_cmd - 0.001, t_cmd, np.ones_like(t_cmd)])
    in_step = t_cmd + 0.013 + 0.002 * rng.standard_normal(t_cmd.size)
    interval = phase_locked_interval_s(commands, in_step)
    assert interval is not None and abs(interval - 0.05) < 1e-9
    assert phase_locked_interval_s(commands, np.arange(1200) / 20.3 + 0.013) is None
