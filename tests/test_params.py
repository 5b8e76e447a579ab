"""Conversions among the Springmann-Cutler, Crassidis and general forms round-trip exactly."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rig.calibration.params import (
    Calibration,
    Crassidis,
    Springmann,
    correction_from_crassidis,
    crassidis_from_correction,
    lower_from_metric,
    lq_decomposition,
    rotation_from_vector,
    springmann_matrix,
    springmann_shape_from_matrix,
)

scales = st.floats(0.5, 1.5)
offsets = st.floats(-50.0, 50.0)
angles = st.floats(-0.3, 0.3)  # rad, about 17 deg: far beyond any real misalignment


@st.composite
def springmanns(draw: st.DrawFn) -> Springmann:
    return Springmann(
        draw(scales), draw(scales), draw(scales),
        draw(offsets), draw(offsets), draw(offsets),
        draw(angles), draw(angles), draw(angles),
    )  # fmt: skip


@st.composite
def rotvecs(draw: st.DrawFn) -> np.ndarray:
    return np.array([draw(st.floats(-1.0, 1.0)) for _ in range(3)])


def test_matrix_matches_springmann_equations() -> None:
    a, b, c, rho, phi, lam = 0.9, 1.1, 1.05, 0.02, -0.03, 0.05
    h = np.array([12.0, -7.0, 30.0])
    m = springmann_matrix(np.array([a, b, c, rho, phi, lam])) @ h
    # Springmann and Cutler eqs. 5-7, written out
    assert np.isclose(m[0], a * h[0])
    assert np.isclose(m[1], b * (h[1] * np.cos(rho) + h[0] * np.sin(rho)))
    assert np.isclose(
        m[2],
        c
        * (
            h[0] * np.sin(lam) + h[1] * np.sin(phi) * np.cos(lam) + h[2] * np.cos(phi) * np.cos(lam)
        ),
    )


@settings(max_examples=200, deadline=None)
@given(springmanns())
def test_springmann_round_trip(sp: Springmann) -> None:
    back = springmann_shape_from_matrix(sp.sensor_matrix)
    expected = np.array([sp.a, sp.b, sp.c, sp.rho, sp.phi, sp.lam])
    np.testing.assert_allclose(back, expected, rtol=1e-12, atol=1e-12)
    cal = Calibration.from_springmann(sp)
    np.testing.assert_allclose(cal.springmann.as_vector(), sp.as_vector(), rtol=1e-12, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(springmanns(), rotvecs())
def test_general_t_splits_into_rotation_and_springmann(sp: Springmann, rv: np.ndarray) -> None:
    rot = rotation_from_vector(rv)
    t = sp.sensor_matrix @ rot
    lower, r = lq_decomposition(t)
    np.testing.assert_allclose(lower, sp.sensor_matrix, atol=1e-12)
    np.testing.assert_allclose(r, rot, atol=1e-12)
    cal = Calibration.from_t_matrix(t, sp.offset_ut)
    np.testing.assert_allclose(cal.t_matrix, t, atol=1e-12)
    np.testing.assert_allclose(cal.correction_matrix @ t, np.eye(3), atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(springmanns(), rotvecs())
def test_crassidis_round_trip(sp: Springmann, rv: np.ndarray) -> None:
    cal = Calibration.from_springmann(sp, rotation=rotation_from_vector(rv))
    w = cal.correction_matrix
    cr, u = crassidis_from_correction(w, cal.offset_ut)
    np.testing.assert_allclose(cr.d_matrix, cr.d_matrix.T, atol=1e-14)
    assert np.all(np.linalg.eigvalsh(np.eye(3) + cr.d_matrix) > 0)
    np.testing.assert_allclose(u @ (np.eye(3) + cr.d_matrix), w, atol=1e-12)  # W = U (I + D)
    np.testing.assert_allclose(u.T @ u, np.eye(3), atol=1e-12)
    w2, o2 = correction_from_crassidis(cr)
    np.testing.assert_allclose(o2, cal.offset_ut, atol=1e-10)
    cr2, u2 = crassidis_from_correction(w2, o2)
    np.testing.assert_allclose(cr2.d_matrix, cr.d_matrix, atol=1e-12)
    np.testing.assert_allclose(cr2.b_ut, cr.b_ut, atol=1e-10)
    np.testing.assert_allclose(u2, np.eye(3), atol=1e-12)
    # Both corrections give the same |h|, so they agree on the scalar calibration.
    m = np.array([[30.0, -10.0, 5.0], [-3.0, 44.0, 1.0]])
    np.testing.assert_allclose(
        np.linalg.norm(cal.apply(m), axis=1),
        np.linalg.norm((m - o2) @ w2.T, axis=1),
        rtol=1e-12,
    )


def test_crassidis_equation_holds() -> None:
    d = np.array([[0.05, 0.01, -0.02], [0.01, -0.03, 0.004], [-0.02, 0.004, 0.08]])
    cr = Crassidis(b_ut=np.array([3.0, -1.0, 2.0]), d_matrix=d)
    w, o = correction_from_crassidis(cr)
    m = np.array([20.0, -5.0, 33.0])
    np.testing.assert_allclose((np.eye(3) + d) @ m - cr.b_ut, w @ (m - o), atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(springmanns(), rotvecs())
def test_scalar_representative_preserves_magnitude(sp: Springmann, rv: np.ndarray) -> None:
    w = np.linalg.inv(sp.sensor_matrix @ rotation_from_vector(rv))
    lower = lower_from_metric(w.T @ w)
    v = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 9.0]])
    np.testing.assert_allclose(
        np.linalg.norm(np.linalg.solve(lower, v.T).T, axis=1), np.linalg.norm(v @ w.T, axis=1)
    )
    cal = Calibration.from_correction(w, sp.offset_ut, scalar=True)
    np.testing.assert_allclose(cal.sensor, lower, atol=1e-12)


def test_apply_inverts_predict() -> None:
    sp = Springmann(0.9, 1.1, 1.02, 1.0, -2.0, 3.0, 0.01, -0.02, 0.03)
    k = np.array([[1.0, -0.5, 0.2], [0.3, 0.0, -1.1]])
    cal = Calibration.from_springmann(
        sp, k, ("i1", "i2"), rotation=rotation_from_vector(np.array([0.1, -0.2, 0.05]))
    )
    rng = np.random.default_rng(0)
    h = rng.normal(size=(50, 3)) * 30
    u = rng.uniform(0, 3, size=(50, 2))
    np.testing.assert_allclose(cal.apply(cal.predict(h, u), u), h, atol=1e-10)


def test_rotation_from_vector_is_a_rotation() -> None:
    rv = np.array([0.3, -1.2, 0.7])
    r = rotation_from_vector(rv)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-13)
    assert np.isclose(np.linalg.det(r), 1.0)
    np.testing.assert_allclose(r @ rv, rv, atol=1e-13)  # the axis is fixed
    assert np.isclose(np.degrees(np.arccos((np.trace(r) - 1) / 2)), np.degrees(np.linalg.norm(rv)))
