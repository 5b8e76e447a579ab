"""The measurement model's parameterizations and exact conversions among them.

The model (ARCHITECTURE.md, contract)::

    m = T h + o + sum_j k_j u_j + n            (raw reading m, true field h, both uT)
    h = W (m - o - sum_j k_j u_j),  W = T^-1   (the general correction)

``T`` factors as ``T = L R``: ``R`` is the mounting rotation (field frame to DUT frame, observable
only when the field vector is known) and ``L`` is lower triangular with a positive diagonal, the
Springmann-Cutler sensor matrix (their eqs. 5-7)::

    L = [[a,          0,                0              ],
         [b sin(rho), b cos(rho),       0              ],
         [c sin(lam), c sin(phi) cos(lam), c cos(phi) cos(lam)]]

The Crassidis / Alonso-Shuster form writes the correction as ``(I + D) m - b = A h`` with ``D``
symmetric: it is the polar decomposition ``W = U (I + D)`` with ``b = (I + D) o``. Angles are radians
here; degrees only at the user boundary.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

SPRINGMANN_KEYS: tuple[str, ...] = ("a", "b", "c", "x0", "y0", "z0", "rho", "phi", "lambda")
"""Order of the Springmann-Cutler parameters in every parameter vector (angles in rad)."""


@dataclass(frozen=True)
class Springmann:
    """Springmann-Cutler parameters: scale factors, offsets (uT) and misalignment angles (rad)."""

    a: float
    b: float
    c: float
    x0: float
    y0: float
    z0: float
    rho: float
    phi: float
    lam: float

    def as_vector(self) -> Array:
        """The nine values in ``SPRINGMANN_KEYS`` order."""
        return np.array(
            [self.a, self.b, self.c, self.x0, self.y0, self.z0, self.rho, self.phi, self.lam]
        )

    @property
    def offset_ut(self) -> Array:
        """The offset vector ``o`` (uT)."""
        return np.array([self.x0, self.y0, self.z0])

    @property
    def sensor_matrix(self) -> Array:
        """The lower-triangular sensor matrix ``L`` (eqs. 5-7)."""
        return springmann_matrix(np.array([self.a, self.b, self.c, self.rho, self.phi, self.lam]))


def springmann_matrix(shape: Array) -> Array:
    """``L`` from ``[a, b, c, rho, phi, lambda]`` (angles rad)."""
    a, b, c, rho, phi, lam = shape
    return np.array(
        [
            [a, 0.0, 0.0],
            [b * np.sin(rho), b * np.cos(rho), 0.0],
            [c * np.sin(lam), c * np.sin(phi) * np.cos(lam), c * np.cos(phi) * np.cos(lam)],
        ]
    )


def springmann_matrix_derivatives(shape: Array) -> Array:
    """``dL/d[a, b, c, rho, phi, lambda]`` as an array of shape (6, 3, 3)."""
    _, b, c, rho, phi, lam = shape
    sr, cr = np.sin(rho), np.cos(rho)
    sp, cp = np.sin(phi), np.cos(phi)
    sl, cl = np.sin(lam), np.cos(lam)
    d = np.zeros((6, 3, 3))
    d[0, 0, 0] = 1.0
    d[1, 1, 0], d[1, 1, 1] = sr, cr
    d[2, 2] = [sl, sp * cl, cp * cl]
    d[3, 1, 0], d[3, 1, 1] = b * cr, -b * sr
    d[4, 2, 1], d[4, 2, 2] = c * cp * cl, -c * sp * cl
    d[5, 2] = [c * cl, -c * sp * sl, -c * cp * sl]
    return d


def springmann_shape_from_matrix(lower: Array) -> Array:
    """``[a, b, c, rho, phi, lambda]`` from a lower-triangular ``L`` with a positive diagonal."""
    if not np.allclose(np.triu(lower, 1), 0.0, atol=1e-12 * max(1.0, float(np.abs(lower).max()))):
        raise ValueError("sensor matrix is not lower triangular")
    if np.any(np.diag(lower) <= 0.0):
        raise ValueError("sensor matrix needs a positive diagonal")
    a = lower[0, 0]
    b = float(np.hypot(lower[1, 0], lower[1, 1]))
    rho = float(np.arctan2(lower[1, 0], lower[1, 1]))
    c = float(np.linalg.norm(lower[2]))
    lam = float(np.arcsin(np.clip(lower[2, 0] / c, -1.0, 1.0)))
    phi = float(np.arctan2(lower[2, 1], lower[2, 2]))
    return np.array([a, b, c, rho, phi, lam])


def lq_decomposition(t: Array) -> tuple[Array, Array]:
    """Split ``T = L R``: ``L`` lower triangular with a positive diagonal, ``R`` orthogonal.

    ``R`` is a proper rotation when ``det T > 0``; a negative determinant (an inverted axis) leaves
    ``R`` improper, which callers report.
    """
    q, u = np.linalg.qr(t.T)
    signs = np.sign(np.diag(u))
    signs[signs == 0] = 1.0
    q = q * signs
    u = signs[:, None] * u
    return u.T, q.T


def lower_from_metric(metric: Array) -> Array:
    """Lower-triangular ``L`` with ``L L^T = metric^-1``, where ``metric = W^T W``.

    This is the scalar-calibration representative: ``|L^-1 v| = |W v|`` for every ``v``.
    """
    t_tt = np.linalg.inv(metric)
    t_tt = 0.5 * (t_tt + t_tt.T)
    return np.asarray(np.linalg.cholesky(t_tt))


@dataclass(frozen=True)
class Crassidis:
    """Crassidis / Alonso-Shuster form ``(I + D) m - b = A h`` (``D`` symmetric, ``b`` uT)."""

    b_ut: Array
    d_matrix: Array


def crassidis_from_correction(w: Array, offset_ut: Array) -> tuple[Crassidis, Array]:
    """Polar-decompose ``W = U (I + D)``; return the Crassidis form and the orthogonal ``U``."""
    left, sv, right_t = np.linalg.svd(w)  # W = U P with U = left right_t, P = right_t^T S right_t
    u = left @ right_t
    p = right_t.T @ np.diag(sv) @ right_t
    del_ = p - np.eye(3)
    d = 0.5 * (del_ + del_.T)
    return Crassidis(b_ut=(np.eye(3) + d) @ offset_ut, d_matrix=d), np.asarray(u)


def correction_from_crassidis(cr: Crassidis) -> tuple[Array, Array]:
    """``(W, o)`` with ``W = I + D`` and ``o = (I + D)^-1 b`` (rotation taken as identity)."""
    w = np.eye(3) + cr.d_matrix
    return w, np.asarray(np.linalg.solve(w, cr.b_ut), dtype=float)


def skew(v: Array) -> Array:
    """Cross-product matrix ``[v]x`` so that ``skew(v) @ x == cross(v, x)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotation_from_vector(rotvec: Array) -> Array:
    """Rotation matrix ``exp([rotvec]x)`` (rotation vector in rad, Rodrigues' formula)."""
    angle = float(np.linalg.norm(rotvec))
    k = skew(np.asarray(rotvec, dtype=float))
    if angle < 1e-8:
        return np.asarray(np.eye(3) + k + 0.5 * (k @ k))
    return np.asarray(
        np.eye(3) + (np.sin(angle) / angle) * k + ((1 - np.cos(angle)) / angle**2) * (k @ k)
    )


@dataclass(frozen=True)
class Calibration:
    """A calibration in the general form: ``T = L R``, offset and current-to-bias coefficients.

    ``sensor`` is the Springmann-Cutler ``L``; ``rotation`` the mounting rotation (identity for a
    scalar calibration, where it is unobservable); ``k_ut_per_unit`` has one row per telemetry
    channel (uT per channel unit, in the raw sensor frame).
    """

    sensor: Array
    offset_ut: Array
    k_ut_per_unit: Array
    channels: tuple[str, ...] = ()
    rotation: Array = field(default_factory=lambda: np.eye(3))

    @property
    def t_matrix(self) -> Array:
        """The distortion ``T = L R`` (raw uT per true uT)."""
        return self.sensor @ self.rotation

    @property
    def correction_matrix(self) -> Array:
        """``W = T^-1``: ``h = W (m - o - sum_j k_j u_j)``."""
        return np.asarray(np.linalg.inv(self.t_matrix))

    @property
    def springmann(self) -> Springmann:
        """Springmann-Cutler parameters of the sensor matrix and offset."""
        shape = springmann_shape_from_matrix(self.sensor)
        return Springmann(*shape[:3], *self.offset_ut, *shape[3:])

    @property
    def crassidis(self) -> Crassidis:
        """Crassidis form of the correction (the rotation part goes to ``A``)."""
        return crassidis_from_correction(self.correction_matrix, self.offset_ut)[0]

    def bias_ut(self, telemetry: Array | None) -> Array:
        """Total bias ``o + sum_j k_j u_j`` per sample, shape (N, 3) (or (3,) without telemetry)."""
        if telemetry is None or self.k_ut_per_unit.size == 0:
            return self.offset_ut
        return self.offset_ut + np.asarray(telemetry, dtype=float) @ self.k_ut_per_unit

    def apply(self, measured_ut: npt.ArrayLike, telemetry: npt.ArrayLike | None = None) -> Array:
        """Corrected field ``W (m - o - sum_j k_j u_j)`` (uT) for raw readings of shape (N, 3)."""
        m = np.asarray(measured_ut, dtype=float)
        u = None if telemetry is None else np.asarray(telemetry, dtype=float)
        if self.k_ut_per_unit.size and u is None:
            raise ValueError(f"this calibration needs telemetry channels {list(self.channels)}")
        return np.asarray((m - self.bias_ut(u)) @ self.correction_matrix.T)

    def predict(self, field_ut: npt.ArrayLike, telemetry: npt.ArrayLike | None = None) -> Array:
        """Noise-free raw reading ``T h + o + sum_j k_j u_j`` (uT) for true fields of shape (N, 3)."""
        h = np.asarray(field_ut, dtype=float)
        u = None if telemetry is None else np.asarray(telemetry, dtype=float)
        return np.asarray(h @ self.t_matrix.T + self.bias_ut(u))

    @staticmethod
    def from_springmann(
        sp: Springmann,
        k_ut_per_unit: npt.ArrayLike | None = None,
        channels: tuple[str, ...] = (),
        rotation: Array | None = None,
    ) -> Calibration:
        """Build from Springmann-Cutler parameters (and optional k rows and mounting rotation)."""
        k = np.zeros((0, 3)) if k_ut_per_unit is None else np.asarray(k_ut_per_unit, float)
        return Calibration(
            sensor=sp.sensor_matrix,
            offset_ut=sp.offset_ut,
            k_ut_per_unit=k.reshape(-1, 3),
            channels=channels,
            rotation=np.eye(3) if rotation is None else np.asarray(rotation, float),
        )

    @staticmethod
    def from_t_matrix(
        t: Array,
        offset_ut: npt.ArrayLike,
        k_ut_per_unit: npt.ArrayLike | None = None,
        channels: tuple[str, ...] = (),
    ) -> Calibration:
        """Build from a general ``T`` (vector calibration): ``T = L R`` by LQ decomposition."""
        lower, rot = lq_decomposition(np.asarray(t, dtype=float))
        k = np.zeros((0, 3)) if k_ut_per_unit is None else np.asarray(k_ut_per_unit, float)
        return Calibration(lower, np.asarray(offset_ut, float), k.reshape(-1, 3), channels, rot)

    @staticmethod
    def from_correction(
        w: Array,
        offset_ut: npt.ArrayLike,
        k_ut_per_unit: npt.ArrayLike | None = None,
        channels: tuple[str, ...] = (),
        *,
        scalar: bool = False,
    ) -> Calibration:
        """Build from a correction ``W``; ``scalar=True`` drops the unobservable rotation."""
        t = np.linalg.inv(np.asarray(w, dtype=float))
        if scalar:
            lower = lower_from_metric(w.T @ w)
            k = np.zeros((0, 3)) if k_ut_per_unit is None else np.asarray(k_ut_per_unit, float)
            return Calibration(lower, np.asarray(offset_ut, float), k.reshape(-1, 3), channels)
        return Calibration.from_t_matrix(t, offset_ut, k_ut_per_unit, channels)
