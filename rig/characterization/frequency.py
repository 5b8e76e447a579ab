"""A magnetometer's response to a sine field: amplitude ratio and phase against the reference,
the reference's own response removed, with sigmas.

Each device's samples (at their own dates: interpolating one to the other's would filter it) and
the commanded set-points are fitted with a constant, a slope and a sine and cosine at the known
frequency over whole cycles; the complex amplitude ``P`` is what the device saw of the field's
``e^(2 pi i f t)``. The field the cage made is ``P_ref / H_ref`` (``H_ref`` the reference's known
response), so the DUT's response is ``H = P_dut H_ref / P_ref`` and the cage's own is
``P_ref / (H_ref P_cmd)``: beyond the frequency where the cage's amplitude falls under 1/sqrt(2)
(its bandwidth) the field is not what was asked, and a point there is marked so.
"""

from __future__ import annotations

import cmath
import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

HALF_POWER = 1.0 / math.sqrt(2.0)
MIN_SAMPLES = 8


@dataclass(frozen=True)
class Phasor:
    """A sine's complex amplitude (the field unit) and the 1-sigma of its modulus (same unit)
    and of its angle (rad), from the fit's residuals."""

    value: complex
    sigma_abs: float
    sigma_angle_rad: float


@dataclass(frozen=True)
class ResponsePoint:
    """At ``f_hz``: the DUT's amplitude ratio and phase (deg, negative: lagging) with 1-sigma,
    and the cage's own (field made over field asked)."""

    f_hz: float
    amplitude: float
    amplitude_sigma: float
    phase_deg: float
    phase_sigma_deg: float
    cage_amplitude: float
    cage_phase_deg: float

    @property
    def within_bandwidth(self) -> bool:
        """The cage made at least half the power asked at this frequency."""
        return self.cage_amplitude >= HALF_POWER


@dataclass(frozen=True)
class SineFit:
    """A least-squares sine: its complex amplitude, the residuals and the (cos, sin) block of the
    inverse normal matrix (times a noise variance: their covariance)."""

    value: complex
    residual: Array
    inv_normal: Array


def sine_fit(t_s: Array, y: Array, f_hz: float, also_hz: tuple[float, ...] = ()) -> SineFit:
    """``y`` at times ``t_s`` (s) fitted with a constant, a slope, a sine at ``f_hz`` and sines at
    ``also_hz`` (the set-points' staircase lines: fitted, not left as noise); the amplitude is
    ``P`` with ``y = Re(P e^(2 pi i f t))``."""
    t = np.asarray(t_s, float)
    if len(t) < MIN_SAMPLES:
        raise ValueError(f"{len(t)} samples: at least {MIN_SAMPLES} are needed for a sine fit")
    design = _design(t, f_hz, also_hz)
    coef, *_ = np.linalg.lstsq(design, np.asarray(y, float), rcond=None)
    resid = np.asarray(y, float) - design @ coef
    inv = np.asarray(np.linalg.inv(design.T @ design)[2:4, 2:4], dtype=np.float64)
    return SineFit(complex(float(coef[2]), -float(coef[3])), resid, inv)  # a cos + b sin


def _design(t: Array, f_hz: float, also_hz: tuple[float, ...]) -> Array:
    """The sine fit's columns at times ``t`` (s): constant, slope, cos and sin at ``f_hz``, then
    cos and sin at each of ``also_hz``."""
    w = 2.0 * math.pi * f_hz * t
    extra = [g(2.0 * math.pi * h * t) for h in also_hz for g in (np.cos, np.sin)]
    return np.column_stack([np.ones_like(t), t - t.mean(), np.cos(w), np.sin(w), *extra])


def phasor(t_s: Array, y: Array, f_hz: float, also_hz: tuple[float, ...] = ()) -> Phasor:
    """One device's phasor at ``f_hz``, its sigma from its own residuals near that frequency."""
    fit = sine_fit(t_s, y, f_hz, also_hz)
    return _with_sigma(fit, _noise_near(np.asarray(t_s, float), fit.residual, f_hz, also_hz))


def relative_phasors(dut: tuple[Array, Array], reference: tuple[Array, Array], f_hz: float,
                     also_dut: tuple[float, ...] = (),
                     also_reference: tuple[float, ...] = ()) -> tuple[Phasor, Phasor]:  # fmt: skip
    """The DUT's and the reference's phasors (each ``(times s, values)``), the sigma of their
    ratio put on the DUT's: the noise near ``f_hz`` of the DUT's residuals less the reference's at
    the same times. Both see the lab field's own changes, which cancel in the ratio; counted in
    each device's sigma they made it fifty times the error."""
    d = sine_fit(*dut, f_hz, also_dut)
    r = sine_fit(*reference, f_hz, also_reference)
    t = np.asarray(dut[0], float)
    apart = d.residual - np.interp(t, np.asarray(reference[0], float), r.residual)
    return _with_sigma(d, _noise_near(t, apart, f_hz, also_dut)), Phasor(r.value, 0.0, 0.0)


def _with_sigma(fit: SineFit, noise_var: float) -> Phasor:
    """The fit's phasor with the 1-sigma of its modulus and angle for a noise variance."""
    cov = fit.inv_normal * noise_var
    value = fit.value
    size = abs(value)
    if size == 0:
        return Phasor(value, math.sqrt(max(float(cov[0, 0]), 0.0)), math.pi)
    a, b = value.real, -value.imag
    # the modulus along the phasor, the angle across it (the covariance of (a, -b) rotated)
    u = np.array([a, -b]) / size
    v = np.array([b, a]) / size
    c = np.array([[cov[0, 0], -cov[0, 1]], [-cov[1, 0], cov[1, 1]]])
    return Phasor(value, math.sqrt(float(u @ c @ u)), math.sqrt(float(v @ c @ v)) / size)


NEIGHBOURS = (-9, -8, -7, -6, -5, -4, -3, -2, 2, 3, 4, 5, 6, 7, 8, 9)
"""The residuals' power is taken at these many frequency bins (1 / the record) from the sine's:
the noise that can move its estimate is the noise near its frequency, not the record's whole
variance (the set-points' higher staircase lines and the lab's mains ripple, far from it, would
make a white-noise sigma twenty times too large)."""


def _noise_near(t: Array, resid: Array, f_hz: float, also_hz: tuple[float, ...]) -> float:
    """The residuals' variance per sample as seen near ``f_hz`` (their least-squares sine
    amplitudes at neighbouring bins, scaled to a white noise of the same density)."""
    span = float(t[-1] - t[0])
    found = []
    for j in NEIGHBOURS:
        g = f_hz + j / span
        # a bin at zero frequency is the fitted constant (and, at 1e-17 Hz after rounding, a
        # near-singular basis whose coefficient came out 1e4 times the noise: issue 54)
        if g < 0.5 / span or any(abs(g - h) < 1.5 / span for h in also_hz):
            continue
        w = 2.0 * math.pi * g * t
        basis = np.column_stack([np.cos(w), np.sin(w)])
        coef, *_ = np.linalg.lstsq(basis, resid, rcond=None)
        # for white noise of variance s2, each coefficient has variance about 2 s2 / n
        found.append(float(coef @ coef) / 4.0 * len(t))
    if not found:
        return float(resid @ resid) / max(len(t) - 4, 1)
    return float(np.mean(found))


def response_point(f_hz: float, dut: Phasor, reference: Phasor, commanded: Phasor,
                   reference_response: complex) -> ResponsePoint:  # fmt: skip
    """The DUT's and the cage's response at ``f_hz`` from the three phasors and the reference's
    own response at that frequency."""
    h = dut.value * reference_response / reference.value
    cage = reference.value / (reference_response * commanded.value)
    rel = math.hypot(dut.sigma_abs / abs(dut.value), reference.sigma_abs / abs(reference.value))
    phase_sigma = math.hypot(dut.sigma_angle_rad, reference.sigma_angle_rad)
    return ResponsePoint(f_hz, abs(h), abs(h) * rel, math.degrees(cmath.phase(h)),
                         math.degrees(phase_sigma), abs(cage), math.degrees(cmath.phase(cage)))  # fmt: skip


def first_order(tau_s: float, integration_s: float, f_hz: float) -> complex:
    """A sensor's response as its configuration states it: a conversion window ``integration_s``
    (a boxcar before the reading's date) and a first-order low-pass ``tau_s``."""
    h = complex(1.0)
    if integration_s > 0:
        x = math.pi * f_hz * integration_s
        h *= (math.sin(x) / x if x else 1.0) * cmath.exp(-1j * x)
    if tau_s > 0:
        h /= complex(1.0, 2.0 * math.pi * f_hz * tau_s)
    return h


def cage_point(f_hz: float, reference: Phasor, commanded: Phasor,
               reference_response: complex) -> ResponsePoint:  # fmt: skip
    """The cage's own response at ``f_hz`` (the field made, as the reference saw it with its
    response removed, over the field asked), its sigma from the reference's; the point's
    ``cage_*`` fields hold the same (the cage is the device measured)."""
    cage = reference.value / (reference_response * commanded.value)
    rel = reference.sigma_abs / abs(reference.value) if reference.value else math.inf
    phase = math.degrees(cmath.phase(cage))
    return ResponsePoint(f_hz, abs(cage), abs(cage) * rel, phase,
                         math.degrees(reference.sigma_angle_rad), abs(cage), phase)  # fmt: skip


def half_power_hz(f_hz: list[float], amplitude: list[float]) -> float | None:
    """The frequency (Hz) where the amplitude first falls under 1/sqrt(2), between the measured
    frequencies (``f_hz`` ascending) by linear interpolation in log frequency; None when it never
    does (the bandwidth is then at least the highest frequency measured)."""
    for k, (f, a) in enumerate(zip(f_hz, amplitude, strict=True)):
        if a >= HALF_POWER:
            continue
        if k == 0:
            return float(f)  # under half power already at the lowest: no better bound
        f0, a0 = f_hz[k - 1], amplitude[k - 1]
        x = (a0 - HALF_POWER) / (a0 - a)
        return float(math.exp(math.log(f0) + x * (math.log(f) - math.log(f0))))
    return None


def corner_hz(f_hz: float, cage_amplitude: float) -> float:
    """The corner (Hz) of a first-order low-pass that is ``cage_amplitude`` at ``f_hz``: the
    cage's high frequencies as one measured point says (infinite when it is not below 0.99)."""
    if cage_amplitude >= 0.99:
        return math.inf
    return f_hz * cage_amplitude / math.sqrt(1.0 - cage_amplitude**2)


def with_systematics(point: ResponsePoint, image: tuple[float, float],
                     timing_sigma_s: float) -> ResponsePoint:  # fmt: skip
    """``point`` with two systematic terms added in quadrature to its sigmas: the staircase's
    images on the sine (``image``: their 1-sigma on the amplitude, relative, and on the phase,
    rad: :func:`rig.characterization.staircase_images.image_spread`) and the devices' relative
    date uncertainty (``timing_sigma_s``, 1-sigma): on the phase its angle ``2 pi f sigma``, on
    the amplitude the loss of a sine whose dates wander by that much within the fit (a phase of
    rms ``phi`` keeps ``E[cos phi] ~ 1 - phi^2 / 2`` of it)."""
    phi = 2.0 * math.pi * point.f_hz * timing_sigma_s
    phase = math.hypot(point.phase_sigma_deg, math.degrees(image[1]), math.degrees(phi))
    amplitude = math.hypot(point.amplitude_sigma, point.amplitude * image[0],
                           point.amplitude * phi**2 / 2.0)  # fmt: skip
    return dataclasses.replace(point, amplitude_sigma=amplitude, phase_sigma_deg=phase)
