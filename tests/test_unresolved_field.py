"""DUT samples whose reference bracket holds a field jump are left out of the calibration data."""

from __future__ import annotations

import numpy as np

from rig.analysis import unresolved_field
from rig.calibration import Samples, calibrate


def tracked_field(t_s: np.ndarray, jump_at_s: float | None, jump_ut: float) -> np.ndarray:
    """A 46 uT field turning at 45 deg/s about z (uT, rows x, y, z), with the whole vector
    held back then catching up by ``jump_ut`` at ``jump_at_s`` (a late command)."""
    angle = np.radians(45.0) * t_s
    field = 46.0 * np.column_stack([np.cos(angle), np.sin(angle), 0.3 * np.ones_like(t_s)])
    if jump_at_s is not None:
        field[t_s < jump_at_s, 0] -= jump_ut  # before the jump the x coil lagged
    return field


def reference_rows(rng: np.random.Generator, jump_at_s: float | None) -> np.ndarray:
    t = np.arange(0.0, 20.0, 0.05)
    field = tracked_field(t, jump_at_s, 3.0) + rng.normal(0.0, 0.005, (t.size, 3))
    return np.column_stack([t, field])


def test_steady_tracking_and_noise_leave_nothing_out() -> None:
    rng = np.random.default_rng(1)
    ref = reference_rows(rng, None)
    dut_t = np.arange(0.013, 19.9, 0.05)
    assert not unresolved_field(ref, dut_t).any()


def test_only_the_samples_around_a_jump_are_left_out() -> None:
    rng = np.random.default_rng(2)
    ref = reference_rows(rng, 10.02)  # between the reference samples at 10.00 and 10.05
    dut_t = np.arange(0.013, 19.9, 0.05)
    out = unresolved_field(ref, dut_t)
    # the second difference flags the reference samples at 10.00 and 10.05; DUT samples in the
    # intervals touching them (9.95-10.10) are left out, nothing else
    assert set(np.round(dut_t[out], 3)) == {9.963, 10.013, 10.063}


def tumbling_field(t_s: np.ndarray) -> np.ndarray:
    """46 uT turning through every direction within 60 s (uT, rows x, y, z)."""
    a, b = 0.785 * t_s, 0.21 * t_s
    return 46.0 * np.column_stack([np.cos(a) * np.cos(b), np.sin(a) * np.cos(b), np.sin(b)])


def test_leaving_them_out_restores_the_fit() -> None:
    """A scalar fit with the DUT samples around five late commands (the field held 0.15 s, then
    caught up, on x only): residual far above the noise with them, near the noise without them."""
    rng = np.random.default_rng(3)

    def with_jumps(t: np.ndarray) -> np.ndarray:
        field = tumbling_field(t)
        for tj in (7.02, 19.52, 31.03, 42.51, 55.04):  # the x supply late: |B| changes too
            late = (t >= tj - 0.15) & (t < tj)
            field[late, 0] = tumbling_field(np.array([tj - 0.15]))[0, 0]
        return field

    t_ref = np.arange(0.0, 60.0, 0.05)
    ref = np.column_stack([t_ref, with_jumps(t_ref) + rng.normal(0, 0.005, (t_ref.size, 3))])
    t_dut = t_ref[:-1] + 0.027
    offset = np.array([2.0, -1.0, 0.5])
    measured = with_jumps(t_dut) * 1.02 + offset + rng.normal(0, 0.02, (t_dut.size, 3))
    field = np.column_stack([np.interp(t_dut, ref[:, 0], ref[:, 1 + i]) for i in range(3)])

    def fit(keep: np.ndarray) -> float:
        s = Samples.build(measured[keep], field_ut=field[keep]).as_scalar()
        return float(calibrate(s, "ml").residual_rms_nt)

    everything = fit(np.ones(t_dut.size, bool))
    out = unresolved_field(ref, t_dut)
    assert 5 <= out.sum() <= 5 * 8, out.sum()  # each event: where the field stops, where it jumps
    kept = fit(~out)
    assert everything > 2.0 * kept and kept < 30.0, (everything, kept)
