"""The coils' field over the working volume: Biot-Savart of each axis's coil pair.

Each axis is a pair of square (or circular, as a many-sided polygon) loops of side (or diameter)
``size_m``, ``spacing_m`` apart, carrying the same current in the same sense. A straight segment
from ``a`` to ``b`` carrying current ``I`` gives at ``p`` (exact, Biot-Savart)::

    B = mu0 I / (4 pi) * (|A| + |B|) / (|A| |B| (|A| |B| + A.B)) * (A x B),  A = a - p, B = b - p

The configured coil matrix ``K`` (uT/A) is the field per ampere at the cage centre, coil
constants and axis directions included; the geometry only shapes it over the volume: column j at
``r`` is ``|K_j| U_j g_j(U_j^T r) / |g_j(0)|``, ``g_j`` the ideal pair along axis j and ``U_j`` the
smallest rotation taking that axis to ``K_j``'s direction (the pair's real, skewed axis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

MU0_UT_M_PER_A = 4e-7 * math.pi * 1e6
"""The vacuum permeability in uT m / A."""
CIRCLE_SIDES = 72
"""Sides of the polygon standing for a circular loop (field within 1e-3 of the circle's)."""


def segment_field_ut(start_m: Array, end_m: Array, points_m: Array) -> Array:
    """Field (uT per A, (N, 3)) of straight segments ``start -> end`` ((S, 3) each) at ``points``
    ((N, 3)), summed over the segments."""
    a = start_m[None, :, :] - points_m[:, None, :]
    b = end_m[None, :, :] - points_m[:, None, :]
    la = np.linalg.norm(a, axis=-1)
    lb = np.linalg.norm(b, axis=-1)
    denom = la * lb * (la * lb + np.einsum("nsk,nsk->ns", a, b))
    factor = MU0_UT_M_PER_A / (4.0 * math.pi) * (la + lb) / denom
    return np.asarray(np.einsum("ns,nsk->nk", factor, np.cross(a, b)))


def loop_corners_m(shape: str, size_m: float, z_m: float) -> Array:
    """Corners ((S, 3), m) of a loop in the plane ``z = z_m``, centred on the z axis, run counter-
    clockwise seen from +z (its field at the centre points along +z)."""
    sides = 4 if shape == "square" else CIRCLE_SIDES
    half = size_m / 2.0
    radius = half * math.sqrt(2.0) if shape == "square" else half
    angles = (
        np.pi / 4.0 + 2.0 * np.pi * np.arange(sides) / sides
        if shape == "square"
        else (2.0 * np.pi * np.arange(sides) / sides)
    )
    return np.column_stack([radius * np.cos(angles), radius * np.sin(angles),
                            np.full(sides, z_m)])  # fmt: skip


@dataclass(frozen=True)
class CoilPair:
    """Two equal coaxial loops along +z (``shape`` "square" or "circular", ``size_m`` side or
    diameter, ``spacing_m`` between their planes), one ampere-turn each."""

    shape: str
    size_m: float
    spacing_m: float

    def field_ut(self, points_m: Array) -> Array:
        """Field (uT per A, (N, 3)) at ``points`` ((N, 3), m, the pair's own frame)."""
        total = np.zeros((points_m.shape[0], 3))
        for z in (-self.spacing_m / 2.0, self.spacing_m / 2.0):
            corners = loop_corners_m(self.shape, self.size_m, z)
            total += segment_field_ut(corners, np.roll(corners, -1, axis=0), points_m)
        return total


def axis_rotation(axis: int, direction: Array) -> Array:
    """The smallest rotation taking the unit vector along ``axis`` to ``direction``."""
    e = np.zeros(3)
    e[axis] = 1.0
    d = direction / np.linalg.norm(direction)
    v, c = np.cross(e, d), float(e @ d)
    if np.linalg.norm(v) < 1e-15:
        return np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.asarray(np.eye(3) + vx + vx @ vx / (1.0 + c))


_TO_Z = (np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], float),  # pair (x, y, z) = cage (y, z, x)
         np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], float),  # pair (x, y, z) = cage (z, x, y)
         np.eye(3))  # fmt: skip
"""Per axis, the rotation taking cage coordinates to a frame whose +z is that axis."""


class CageCoils:
    """The three coil pairs around a coil matrix: the field per ampere at any position.

    ``pairs[j]`` is axis j's pair; ``coil_matrix_ut_per_a`` is ``K`` at the centre.
    """

    def __init__(self, pairs: tuple[CoilPair, ...], coil_matrix_ut_per_a: Array) -> None:
        self.pairs = pairs
        self.k_centre = np.asarray(coil_matrix_ut_per_a, float)
        self._rotations = []
        self._gains = []
        for j, pair in enumerate(pairs):
            column = self.k_centre[:, j]
            self._rotations.append(axis_rotation(j, column))
            centre = pair.field_ut(np.zeros((1, 3)))[0, 2]
            self._gains.append(float(np.linalg.norm(column)) / centre)

    def matrix_at(self, position_m: Array) -> Array:
        """``K`` (uT/A, 3x3) at ``position_m`` (m, cage frame from the centre)."""
        cols = []
        for j, pair in enumerate(self.pairs):
            u = self._rotations[j]
            local = _TO_Z[j] @ (u.T @ np.asarray(position_m, float))
            b_local = pair.field_ut(local[None, :])[0]
            cols.append(self._gains[j] * (u @ (_TO_Z[j].T @ b_local)))
        return np.column_stack(cols)
