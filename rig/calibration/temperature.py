"""Temperature dependence of the DUT: offset and scale per kelvin.

The model with the DUT temperature ``T`` (any unit of kelvin size: K or degrees C), about a
reference ``T_ref`` (the mean of the data unless given):

    m = (1 + s_T dT) T0 h + o + o_T dT + sum_j k_j u_j,    dT = T - T_ref

The offset coefficient ``o_T`` (uT/K, per axis) is a telemetry channel of its own with value
``dT`` (:data:`CHANNEL`): linear, with its sigma and Cramer-Rao bound like every current-to-bias
coefficient. The scale coefficient ``s_T`` (1/K, common to the three axes: the sensing element's
temperature coefficient) acts on the field the DUT sees, so it is profiled
(:mod:`rig.calibration.profiled`): the reference is scaled by ``1 + s_T dT`` and everything else
refit. Per-axis scale coefficients are not modelled.
"""

from __future__ import annotations

import numpy as np

from rig.calibration.params import Array
from rig.calibration.profiled import Profiled
from rig.calibration.residuals import Samples
from rig.errors import CalibrationError

CHANNEL = "temperature"
"""Name of the offset-per-kelvin channel (its k is the offset coefficient, uT/K)."""
MAX_SCALE_PER_K = 0.005
"""Search range of the scale coefficient (1/K): +-5000 ppm/K."""
MIN_SPAN_K = 0.5
"""A temperature that moves less than this (K) over the data cannot reveal a coefficient."""


def with_temperature_channel(s: Samples, temperature: Array, reference: float) -> Samples:
    """``s`` with ``dT = T - reference`` appended as the telemetry channel :data:`CHANNEL`."""
    t = np.asarray(temperature, float).reshape(-1)
    if t.shape != (s.n,) or not np.all(np.isfinite(t)):
        raise CalibrationError("--temperature: one finite value per sample is needed")
    if np.ptp(t) < MIN_SPAN_K:
        raise CalibrationError(
            f"--temperature: it spans {np.ptp(t):.2f} K, less than {MIN_SPAN_K} K: the data cannot"
            " show a temperature coefficient; record over a temperature range (a thermal soak)"
        )
    if CHANNEL in s.channels:
        raise CalibrationError(f"--telemetry already has a channel named {CHANNEL}: rename it")
    u = np.column_stack([s.telemetry, t - reference])
    return Samples(
        s.measured_ut, s.field_magnitude_ut, u, (*s.channels, CHANNEL), s.field_ut, s.holds
    )


def scale_parameter(s: Samples) -> Profiled:
    """The scale coefficient (1/K) of samples that carry the :data:`CHANNEL` column."""
    d_t = s.telemetry[:, s.channels.index(CHANNEL)].copy()
    field = None if s.field_ut is None else s.field_ut.copy()
    magnitude = s.field_magnitude_ut.copy()

    def apply(data: Samples, s_t: float) -> Samples:
        gain = 1.0 + s_t * d_t
        scaled = None if field is None else field * gain[:, None]
        return Samples(data.measured_ut, magnitude * gain, data.telemetry, data.channels, scaled)

    return Profiled("temperature", "scale_per_k", "1/K", (-MAX_SCALE_PER_K, MAX_SCALE_PER_K),
                    1e-6, apply, label="scale per kelvin", shown_unit="ppm/K", shown_scale=1e6)  # fmt: skip
