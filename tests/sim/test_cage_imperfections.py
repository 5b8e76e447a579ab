"""The simulated cage's own imperfections against physics written out independently: the coils'
field over the volume (textbook loop formulas, the dipole far field), the lab field (gradient
laws, a 1/f spectrum, traffic by position) and the supplies' gain drift the read-back hides."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.signal import welch

from sim.coils import CageCoils, CoilPair, loop_corners_m, segment_field_ut
from sim.config import SimConfigError, load_config
from sim.lab_field import LabField
from sim.physics import CagePhysics

MU0 = 4e-7 * math.pi * 1e6  # uT m / A
K = np.array([[40.20, 0.85, -0.42], [0.61, 39.10, 0.37], [-0.28, 0.74, 41.30]])


def loop_field(shape: str, size_m: float, points: np.ndarray) -> np.ndarray:
    corners = loop_corners_m(shape, size_m, 0.0)
    return segment_field_ut(corners, np.roll(corners, -1, axis=0), points)


def square_on_axis_ut(side_m: float, z_m: float) -> float:
    """Field (uT per A) on the axis of a square loop (Griffiths, problem 5.8 generalized)."""
    return (
        MU0
        * side_m**2
        / (2 * math.pi * (z_m**2 + side_m**2 / 4) * math.sqrt(z_m**2 + side_m**2 / 2))
    )


def test_a_square_loop_gives_the_textbook_field() -> None:
    side = 2.0
    got = loop_field("square", side, np.array([[0, 0, 0.0], [0, 0, 0.7], [0, 0, -1.3]]))
    assert got[0, 2] == pytest.approx(2 * math.sqrt(2) * MU0 / (math.pi * side), rel=1e-12)
    assert got[1, 2] == pytest.approx(square_on_axis_ut(side, 0.7), rel=1e-12)
    assert got[2, 2] == pytest.approx(square_on_axis_ut(side, -1.3), rel=1e-12)
    np.testing.assert_allclose(got[:, :2], 0.0, atol=1e-12)


def test_a_circular_loop_gives_mu0_i_over_2r() -> None:
    got = loop_field("circular", 2.0, np.zeros((1, 3)))[0]
    assert got[2] == pytest.approx(MU0 / 2.0, rel=1e-3)  # a 72-gon: within 1e-3 of the circle


def test_a_square_helmholtz_pair_is_flat_to_fourth_order() -> None:
    """At 0.5445 side spacing the second derivative vanishes: the error grows as r^4 (x16 per
    doubling of the distance), not r^2 (x4)."""
    pair = CoilPair("square", 2.0, 0.5445 * 2.0)
    centre = pair.field_ut(np.zeros((1, 3)))[0, 2]
    errors = [abs(pair.field_ut(np.array([[0, 0, z]]))[0, 2] / centre - 1) for z in (0.05, 0.1)]
    assert 12 < errors[1] / errors[0] < 20 and errors[1] < 1e-4, errors
    wrong = CoilPair("square", 2.0, 1.0 * 2.0)  # spaced a side apart: quadratic
    centre = wrong.field_ut(np.zeros((1, 3)))[0, 2]
    quad = [abs(wrong.field_ut(np.array([[0, 0, z]]))[0, 2] / centre - 1) for z in (0.05, 0.1)]
    assert 3.5 < quad[1] / quad[0] < 4.5, quad


def test_the_coils_give_k_at_the_centre_and_a_dipole_far_away() -> None:
    pairs = tuple(CoilPair("square", s, 0.5445 * s) for s in (2.0, 1.9, 1.8))
    coils = CageCoils(pairs, K)
    np.testing.assert_allclose(coils.matrix_at(np.zeros(3)), K, atol=1e-12)
    # 10 cm off centre: the inhomogeneity of a 2 m cage is of order 1e-4
    off = coils.matrix_at(np.array([0.0, 0.0, -0.1]))
    assert 1e-5 < np.abs(off - K).max() / 40 < 3e-4
    # far on the x coils' axis: two loops of area a^2 are a dipole 2 a^2 (per ampere-turn),
    # on axis B = mu0 / (4 pi) 2 m / r^3; the centre field of the pair fixes the turns
    r, a, d = 30.0, 2.0, 0.5445 * 2.0
    centre_per_turn = 2 * square_on_axis_ut(a, d / 2)
    turns = np.linalg.norm(K[:, 0]) / centre_per_turn
    expected = turns * MU0 / (4 * math.pi) * 2 * (2 * a * a) / r**3
    axis = K[:, 0] / np.linalg.norm(K[:, 0])  # the pair's real (skewed) axis is K's column
    far = coils.matrix_at(r * axis)[:, 0]
    assert np.linalg.norm(far) == pytest.approx(expected, rel=0.01)
    assert np.degrees(np.arccos(far @ axis / np.linalg.norm(far))) < 0.01  # on its axis: along it
    # off that axis by theta (here the 0.87 deg skew, on the cage's x axis) a dipole's field
    # turns by atan(3 sin(theta) cos(theta) / (3 cos^2(theta) - 1)), about 1.5 theta
    theta = math.acos(axis[0])
    off = coils.matrix_at(np.array([r, 0.0, 0.0]))[:, 0]
    turn = math.atan2(3 * math.sin(theta) * math.cos(theta), 3 * math.cos(theta) ** 2 - 1)
    assert math.degrees(math.acos(off @ axis / np.linalg.norm(off))) == pytest.approx(
        math.degrees(turn), rel=0.02
    )


def test_a_gradient_with_curl_or_divergence_is_refused() -> None:
    cfg = load_config().ambient
    for bad in (((0.01, 0, 0), (0, 0, 0), (0, 0, 0)), ((0, 0.01, 0), (0, 0, 0), (0, 0, 0))):
        with pytest.raises(SimConfigError, match="symmetric with zero trace"):
            LabField(replace(cfg, gradient_ut_per_m=bad), 1)


def test_the_flicker_noise_has_a_1_over_f_spectrum_and_its_rms() -> None:
    cfg = replace(load_config().ambient, flicker_ut=0.002, diurnal_amplitude_ut=(0.0, 0.0, 0.0))
    lab = LabField(cfg, 3)
    t = np.arange(0.0, 200_000.0, 2.0)
    x = np.array([lab.uniform_ut(float(v)) for v in t])
    assert np.std(x, axis=0) == pytest.approx([0.002] * 3, rel=0.35)
    # 1/f: the same power in every decade (white noise would give 10 and 100 times more)
    f, psd = welch(x[:, 0], fs=0.5, nperseg=65536)
    df = f[1] - f[0]
    decades = [psd[(f >= lo) & (f < 10 * lo)].sum() * df for lo in (1e-4, 1e-3, 1e-2)]
    assert max(decades) / min(decades) < 1.6, decades


def test_traffic_comes_and_goes_and_is_stronger_nearer_the_street() -> None:
    cfg = replace(load_config().ambient, traffic_rate_per_h=4.0, traffic_field_ut=0.01,
                  traffic_distance_m=15.0, traffic_duration_s=600.0)  # fmt: skip
    lab = LabField(cfg, 5)
    times = np.arange(0.0, 2 * 86400.0, 30.0)
    present = np.array([len(lab.vehicles_at(float(t))) for t in times])
    # Poisson arrivals at 4 per hour staying 10 min: on average 0.67 present
    assert 0.4 < present.mean() < 1.0 and present.max() >= 2 and (present == 0).any()
    # the same at any evaluation order, and from a fresh copy of the same seed
    again = LabField(cfg, 5)
    for t in (150_000.0, 3_600.0, 90_000.0):
        pts = np.array([[0.0, 0.0, 0.0], [8.0, 0.0, 0.0]])
        np.testing.assert_array_equal(lab.local_ut(t, pts), again.local_ut(t, pts))
    # a sensor 10 m nearer the street sees the vehicles more strongly than the centre
    busy = [float(t) for t in times if len(lab.vehicles_at(float(t))) == 1][:50]
    centre = [np.linalg.norm(lab.local_ut(t, np.zeros((1, 3)))) for t in busy]
    near = [np.linalg.norm(lab.local_ut(t, np.array([[0.0, 10.0, 0.0]]))) for t in busy]
    assert np.median(near) > 3 * np.median(centre) and 0.002 < np.median(centre) < 0.05


def test_the_supplies_gain_drift_shows_in_the_field_not_in_their_read_back() -> None:
    physics = CagePhysics(load_config(), start_s=0.0)
    for axis in range(3):
        supply = physics.coil_supply[axis]
        supply.set_voltage(40.0, 0.0)
        supply.set_current(1.0, 0.0)
        supply.set_output(True, 0.0)
    early, late = 10.0, 10.0 + 3 * 3600.0
    assert physics.coil_currents(late) == pytest.approx(physics.coil_currents(early), abs=1e-12)
    coil_part = [physics.field_ut(t, noise=False) - physics.ambient_ut(t, noise=False)
                 for t in (early, late)]  # fmt: skip
    cfgs = sorted((s for s in physics.cfg.supplies if s.axis is not None), key=lambda s: s.axis)
    lab_k = [physics.lab.lab_temperature_c(t) for t in (early, late)]
    ppm = [[s.gain_ppm + s.gain_drift_ppm_per_h * t / 3600 + s.gain_ppm_per_k * k for s in cfgs]
           for t, k in zip((early, late), lab_k, strict=True)]  # fmt: skip
    for part, p in zip(coil_part, ppm, strict=True):
        np.testing.assert_allclose(part, K @ (1 + 1e-6 * np.array(p)), rtol=1e-12)
    assert np.abs(coil_part[1] - coil_part[0]).max() > 1e-4  # > 0.1 nT: visible in the field


def test_each_magnetometer_sees_the_field_where_it_sits() -> None:
    physics = CagePhysics(load_config(), start_s=0.0)
    ref = physics.cfg.magnetometer("reference")
    assert ref.position_m != (0.0, 0.0, 0.0)
    for axis in range(3):
        supply = physics.coil_supply[axis]
        supply.set_voltage(40.0, 0.0)
        supply.set_current(1.0, 0.0)
        supply.set_output(True, 0.0)
    t = 5.0
    at_ref = physics.field_at_ut("reference", t, noise=False)
    at_dut = physics.field_at_ut("dut", t, noise=False)
    np.testing.assert_allclose(at_dut, physics.field_ut(t, noise=False), atol=1e-12)
    gradient = np.array(physics.cfg.ambient.gradient_ut_per_m) @ np.array(ref.position_m)
    coils = (physics.coil_matrix_at["reference"] - K) @ physics.true_coil_currents(t)
    np.testing.assert_allclose(at_ref - at_dut, gradient + coils, atol=1e-3)  # traffic aside
    assert 5e-4 < np.linalg.norm(at_ref - at_dut) < 0.02  # 0.5-20 nT over 8 cm


def test_a_configuration_without_the_new_keys_is_the_ideal_cage() -> None:
    text = load_config().source
    cfg = load_config()
    plain = replace(
        cfg,
        cage=replace(cfg.cage, coil_shape=None),
        ambient=replace(cfg.ambient, gradient_ut_per_m=((0.0,) * 3,) * 3,
                        diurnal_amplitude_ut=(0.0,) * 3, flicker_ut=0.0, traffic_rate_per_h=0.0,
                        lab_temperature_swing_c=0.0),
        supplies=tuple(replace(s, gain_ppm=0.0, gain_drift_ppm_per_h=0.0, gain_ppm_per_k=0.0)
                       for s in cfg.supplies),
    )  # fmt: skip
    assert text
    physics = CagePhysics(plain, start_s=0.0)
    np.testing.assert_array_equal(physics.coil_matrix_at["reference"], K)
    assert physics.coil_gains(7200.0) == pytest.approx([1.0, 1.0, 1.0], abs=0)
