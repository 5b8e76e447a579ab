"""Offset noise drawn independently of the project's noise model (issue 54's audits): white noise,
flicker shaped in the frequency domain (a one-sided spectrum ``h / f``, whose Allan variance is
``2 ln 2 h``) and a random walk of Gaussian steps. tests/test_offset_noise.py checks each against
allantools' Allan variance; bench/bench_characterization_audit.py draws its records from it."""

from __future__ import annotations

import math

import numpy as np


def offsets(rng: np.random.Generator, n: int, rate_hz: float, white_nt: float, flicker_nt: float,
            walk_nt_per_sqrt_h: float) -> np.ndarray:  # fmt: skip
    """(n,) offsets (nT) at ``rate_hz``: white of sigma ``white_nt`` per sample, flicker of flat
    Allan deviation ``flicker_nt`` (nT) and a random walk of ``walk_nt_per_sqrt_h``."""
    y = white_nt * rng.standard_normal(n)
    if flicker_nt > 0:
        m = 2 * n  # twice as long, then cut: the periodic FFT draw's ends do not meet
        f = np.fft.rfftfreq(m, 1.0 / rate_hz)
        amp = np.zeros_like(f)
        amp[1:] = np.sqrt(flicker_nt**2 / (2.0 * math.log(2.0)) / f[1:] * rate_hz * m / 4.0)
        spec = amp * (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f)))
        y += np.fft.irfft(spec, m)[:n]
    if walk_nt_per_sqrt_h > 0:
        y += np.cumsum(rng.standard_normal(n)) * walk_nt_per_sqrt_h / math.sqrt(3600.0 * rate_hz)
    return y
