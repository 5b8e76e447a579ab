"""Prefilters applied to a file's columns before fitting."""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from rig.io.csv_table import Array


def moving_median(x: Array, window: int) -> Array:
    """Centred moving median of each column of ``x`` (N, C) over ``window`` samples (odd); the
    ends repeat the first and last rows, so the output has the input's length and no lag."""
    if window < 1 or window % 2 == 0:
        raise ValueError(f"the median window must be odd and positive, got {window}")
    half = window // 2
    padded = np.pad(np.asarray(x, float), ((half, half), (0, 0)), mode="edge")
    out: Array = np.median(sliding_window_view(padded, window, axis=0), axis=-1)
    return out
