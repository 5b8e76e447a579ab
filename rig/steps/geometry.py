"""Field directions for sweeps: nearly uniform on the sphere, in a seeded random order."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


def fibonacci_directions(n: int) -> Array:
    """``n`` nearly uniform unit vectors (Fibonacci sphere)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z**2)
    phi = math.pi * (1.0 + math.sqrt(5.0)) * k
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def sphere_fields(n: int, magnitude_ut: tuple[float, float], seed: int) -> Array:
    """``n`` fields (uT): Fibonacci directions and magnitudes spread over ``[low, high]``, both
    in a random order from ``seed``."""
    rng = np.random.default_rng(seed)
    dirs = fibonacci_directions(n)[rng.permutation(n)]
    lo, hi = magnitude_ut
    mags = np.linspace(lo, hi, n) if hi > lo else np.full(n, lo)
    return dirs * mags[rng.permutation(n)][:, None]
