"""What the set-points' staircase puts on a sine fitted to a device's samples, as a 1-sigma.

A sine made of set-points at ``rate_hz`` is a staircase: held values (a zero-order hold)
smoothed by the coils' L/R. A device samples it at its own instants, which fall somewhere in
each hold: what it reads of the sine is the smooth field's plus a ripple that, sampled, aliases
onto frequencies near the sine or onto the sine itself, where no fit can take it apart. How much
depends on where the samples fall in the holds: sampled late in every hold, a held sine reads as
a delayed one (a phase), with a spread of places in the hold also as a smaller one (an
amplitude). A device's clock runs free of the set-points', so where its samples fall is a random
draw; the error on the DUT's response (its readings over the reference's) is the difference of
two such draws.

:func:`image_spread` computes it for the devices' own sample times: the staircase of a unit sine
through a first-order coil (the cage's measured corner) is sampled at those times shifted across
one hold, fitted as the devices' readings are, and the spread of the fitted phasor about the
smooth field's is each device's; the two add in quadrature. The devices are taken to sample
instantly, the most of the ripple a device can see (a device's own low-pass only lessens it).
Checked on exact staircases at commensurate and free rates (``tests/test_frequency_fit.py``):
rms z 0.86-1.31 per component, where a bound counted on both components had been 2-5 times wide
on the amplitude and, counting one device, exceeded 1.7 times on exact data.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.signal import lfilter

from rig.characterization.frequency import sine_fit

Array = npt.NDArray[np.float64]

DRAWS = 16
"""Places in the hold tried per device (evenly spread over one set-point period)."""
FORGET_TAUS = 20.0
"""The staircase starts this many coil time constants before the first sample (e^-20)."""


@dataclass(frozen=True)
class ImageSpread:
    """The staircase images' 1-sigma on a DUT's response: on its amplitude ratio (relative) and
    on its phase (rad)."""

    amplitude: float
    phase_rad: float


def held_field(t_s: Array, f_hz: float, rate_hz: float, tau_s: float) -> Array:
    """A unit sine's set-points (``sin(2 pi f k / rate)`` at ``k / rate_hz`` s) through a zero-order
    hold and a first-order coil of time constant ``tau_s`` (s; 0: the hold itself), at times
    ``t_s`` (s, at least 0), from its steady state."""
    t = np.asarray(t_s, float)
    lead = math.ceil(FORGET_TAUS * tau_s * rate_hz) + 2
    k = np.arange(-lead, math.floor(float(t.max()) * rate_hz) + 2)
    v = np.sin(2.0 * math.pi * f_hz * k / rate_hz)
    held = np.floor(t * rate_hz + 1e-12).astype(int) + lead  # the set-point in force
    if tau_s <= 0:
        return np.asarray(v[held])
    a = math.exp(-1.0 / (rate_hz * tau_s))
    after = lfilter([1.0 - a], [1.0, -a], v)  # the coil's value as each hold ends
    before = np.concatenate([[0.0], after[:-1]])  # ... and as each begins
    since = t - (held - lead) / rate_hz
    return np.asarray(v[held] + (before[held] - v[held]) * np.exp(-since / tau_s))


def smooth_phasor(f_hz: float, rate_hz: float, tau_s: float) -> complex:
    """The held and smoothed field's own phasor at ``f_hz`` (``y = Re(P e^(2 pi i f t))``): the
    set-points' sine (``-i``), the hold's sinc and half-period delay, the coil's low-pass."""
    x = math.pi * f_hz / rate_hz
    hold = math.sin(x) / x * complex(math.cos(x), -math.sin(x))
    return -1j * hold / complex(1.0, 2.0 * math.pi * f_hz * tau_s)


def image_spread(f_hz: float, rate_hz: float, fits: Sequence[tuple[Array, tuple[float, ...]]],
                 corner_hz: float) -> ImageSpread:  # fmt: skip
    """The 1-sigma the staircase's images give a DUT's response at ``f_hz`` from set-points at
    ``rate_hz`` through a cage of first-order ``corner_hz`` (Hz; infinite: no fall). ``fits``:
    each device's (sample times s, lines fitted beside the sine Hz), as its phasor was fitted."""
    tau = 0.0 if not math.isfinite(corner_hz) else 1.0 / (2.0 * math.pi * corner_hz)
    smooth = smooth_phasor(f_hz, rate_hz, tau)
    re2 = im2 = 0.0
    for t_s, also in fits:
        t = np.asarray(t_s, float) - float(t_s[0])
        errors = []
        for j in range(DRAWS):
            shifted = t + (j + 0.5) / (DRAWS * rate_hz)
            fitted = sine_fit(shifted, held_field(shifted, f_hz, rate_hz, tau), f_hz, also)
            errors.append(fitted.value / smooth - 1.0)
        e = np.asarray(errors, complex)
        e -= e.mean()  # what every device reads alike is the cage's, and cancels in the ratio
        re2 += float(np.mean(e.real**2))
        im2 += float(np.mean(e.imag**2))
    return ImageSpread(math.sqrt(re2), math.sqrt(im2))
