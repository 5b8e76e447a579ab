"""Synthetic data with known truth, for tests, benchmarks and the example data set.

Pure numpy and seeded: the same arguments always give the same arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rig.calibration.params import Array, Calibration, Springmann, rotation_from_vector
from rig.calibration.residuals import Samples

ORBIT_PERIOD_S = 5820.0
"""A 650 km low Earth orbit (RAX: 97 min)."""
RAX_CHANNELS = ("i_px", "i_mx", "i_py", "i_my", "i_eps")
RAX_TRUTH = Springmann(
    a=0.890, b=0.910, c=1.130, x0=-0.687, y0=9.909, z0=-7.701,
    rho=np.radians(-1.039), phi=np.radians(-3.974), lam=np.radians(5.019),
)  # fmt: skip
"""The PNI magnetometer of Springmann and Cutler, Table 1, calibration 3."""
RAX_K_UT_PER_A = np.array(
    [[1.8, -0.9, 0.4], [-1.2, 1.5, -0.3], [0.6, 2.1, -1.0], [-0.5, -1.7, 1.3], [0.8, -0.6, 1.9]]
)
"""Current-to-bias coefficients (uT/A): four solar panels (+x, -x, +y, -y) and the EPS."""


@dataclass(frozen=True)
class SyntheticCase:
    """Noisy samples with the truth that made them."""

    time_s: Array
    samples: Samples
    truth: Calibration
    noise_ut: float
    field_ut: Array
    """True field in the field (reference) frame, (N, 3) uT."""
    temperature: Array | None = None
    """DUT temperature per sample (degrees C), when the truth has temperature coefficients."""
    profiled_truth: tuple[tuple[str, float], ...] = ()
    """True values of the parameters ``calibrate`` profiles (delays, the scale per kelvin), by
    their parameter-table label; the readings then do not follow ``truth.predict`` alone."""

    def with_noise(self, seed: int) -> SyntheticCase:
        """Same truth and field, a new noise draw (cases without profiled parameters)."""
        if self.profiled_truth:
            raise ValueError("with_noise: the readings of this case are not truth.predict")
        rng = np.random.default_rng(seed)
        clean = self.truth.predict(self.field_ut, self.samples.telemetry)
        m = clean + self.noise_ut * rng.standard_normal(clean.shape)
        s = self.samples
        return SyntheticCase(
            self.time_s,
            Samples(m, s.field_magnitude_ut, s.telemetry, s.channels, s.field_ut, s.holds),
            self.truth,
            self.noise_ut,
            self.field_ut,
        )


def _rotations(axis: Array, angles: Array) -> Array:
    """Rodrigues rotation matrices about a unit axis, shape (N, 3, 3)."""
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.asarray(np.eye(3) + s * kx + (1 - c) * (kx @ kx))


def rax_like(
    n_samples: int = 6000,
    *,
    seed: int = 1,
    noise_ut: float = 0.1,
    dt_s: float = 1.0,
    channels: int = 5,
    start_s: float = 0.0,
) -> SyntheticCase:
    """A tumbling CubeSat in a 97 min orbit, after Springmann and Cutler's RAX case.

    |h| swings between 20 and 50 uT twice per orbit; panel currents follow the sun direction on
    each of the +x, -x, +y, -y faces and drop to zero in eclipse (38 % of the orbit); the EPS draws
    0.35 A plus 1.2 A beacon spikes of 2 s every 20 s. ``channels`` keeps the first 0-5 of those;
    more than 5 adds switched loads (:func:`_switched_loads`). Only the field magnitude is a
    reference here (attitude independent), as on orbit. ``start_s``: time of the first sample
    (s), so that long series can be made in pieces.
    """
    if channels > len(RAX_CHANNELS):
        return _with_switched_loads(
            rax_like(n_samples, seed=seed, noise_ut=noise_ut, dt_s=dt_s, start_s=start_s),
            channels - len(RAX_CHANNELS),
            seed,
        )
    rng = np.random.default_rng(seed)
    t = start_s + np.arange(n_samples, dtype=float) * dt_s
    phase = 2 * np.pi * t / ORBIT_PERIOD_S
    magnitude = 35.0 - 15.0 * np.cos(2 * phase)
    direction_i = np.column_stack([np.cos(2 * phase), 0.3 * np.sin(phase), np.sin(2 * phase)])
    direction_i /= np.linalg.norm(direction_i, axis=1)[:, None]
    # Tumbling: two incommensurate spins make the field sweep the whole body sphere.
    body = _rotations(np.array([0.0, 0.0, 1.0]), np.radians(2.1) * t) @ _rotations(
        np.array([1.0, 0.4, 0.0]), np.radians(0.83) * t
    )
    field_b = np.einsum("nji,nj->ni", body, magnitude[:, None] * direction_i)
    sun_b = np.einsum("nji,j->ni", body, np.array([0.6, 0.8, 0.0]))
    in_sun = (phase % (2 * np.pi)) < 0.62 * 2 * np.pi
    normals = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    panels = 0.5 * np.clip(sun_b @ normals.T, 0.0, None) * in_sun[:, None]
    beacon = (t % 20.0) < 2.0
    eps = 0.35 + 0.05 * in_sun + 1.2 * beacon
    telemetry_all = np.round(np.column_stack([panels, eps]), 3)  # 1 mA telemetry resolution
    telemetry = telemetry_all[:, :channels]
    names = RAX_CHANNELS[:channels]
    truth = Calibration.from_springmann(RAX_TRUTH, RAX_K_UT_PER_A[:channels], names)
    full_truth = Calibration.from_springmann(RAX_TRUTH, RAX_K_UT_PER_A, RAX_CHANNELS)
    m = full_truth.predict(field_b, telemetry_all) + noise_ut * rng.standard_normal((n_samples, 3))
    samples = Samples(m, np.linalg.norm(field_b, axis=1), telemetry, names, None)
    return SyntheticCase(t, samples, truth, noise_ut, field_b)


def _switched_loads(t: Array, count: int, seed: int) -> Array:
    """``count`` loads switched on and off (heaters, wheels, a payload): each holds its level
    (0.1-2 A, 1 mA resolution) for a dwell drawn around its own period (7-300 s), off a third of
    the time. Seeded by ``seed`` and the load's index, so pieces of a series made with the same
    seed at different ``t`` are one series."""
    out = np.empty((t.size, count))
    for j in range(count):
        rng = np.random.default_rng([seed, 1000 + j])
        period = rng.uniform(7.0, 300.0)
        slot = (np.floor(t / period).astype(np.int64) + rng.integers(1 << 20)).astype(np.uint64)
        # The level of slot k: a (Fibonacci) hash of k, so pieces of the series agree.
        u01 = ((slot * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(11)) / float(1 << 53)
        level = np.where(u01 < 1 / 3, 0.0, 0.1 + 1.9 * (u01 - 1 / 3) * 1.5)
        out[:, j] = np.round(level, 3)
    return out


def _with_switched_loads(case: SyntheticCase, count: int, seed: int) -> SyntheticCase:
    """``case`` with ``count`` switched loads added to its telemetry and its readings."""
    extra = _switched_loads(case.time_s, count, seed)
    k_extra = np.random.default_rng([seed, 999]).uniform(-2.0, 2.0, size=(count, 3))
    names = case.samples.channels + tuple(f"load{j + 1:02d}" for j in range(count))
    s = case.samples
    telemetry = np.hstack([s.telemetry, extra])
    m = s.measured_ut + extra @ k_extra  # the bias is additive in the raw frame
    truth = case.truth
    truth = Calibration(truth.sensor, truth.offset_ut, np.vstack([truth.k_ut_per_unit, k_extra]),
                        names, truth.rotation)  # fmt: skip
    samples = Samples(m, s.field_magnitude_ut, telemetry, names, None)
    return SyntheticCase(case.time_s, samples, truth, case.noise_ut, case.field_ut)


def cage_like(
    n_samples: int = 2000,
    *,
    seed: int = 2,
    noise_ut: float = 0.05,
    channels: int = 2,
    mounting_deg: tuple[float, float, float] = (1.5, -2.0, 3.0),
) -> SyntheticCase:
    """A Helmholtz-cage sweep: field vectors of 10-80 uT in all directions, load-current steps.

    Each load channel steps through 0, 1, 2, 3 A in blocks (so it returns to zero), independently
    of the others; the DUT is mounted with a small rotation ``mounting_deg`` (rotation vector, deg).
    """
    rng = np.random.default_rng(seed)
    direction = rng.standard_normal((n_samples, 3))
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    magnitude = rng.uniform(10.0, 80.0, n_samples)
    field = direction * magnitude[:, None]
    block = max(n_samples // 40, 1)
    levels = rng.integers(0, 4, size=(n_samples // block + 1, channels)).astype(float)
    telemetry = np.repeat(levels, block, axis=0)[:n_samples]
    names = tuple(f"load{j + 1}_a" for j in range(channels))
    sp = Springmann(1.02, 0.97, 1.05, 2.5, -1.2, 0.8, np.radians(0.8), np.radians(-0.6),
                    np.radians(1.1))  # fmt: skip
    k = rng.uniform(-1.5, 1.5, size=(channels, 3))
    rot = rotation_from_vector(np.radians(np.array(mounting_deg)))
    truth = Calibration.from_springmann(sp, k, names, rotation=rot)
    m = truth.predict(field, telemetry) + noise_ut * rng.standard_normal((n_samples, 3))
    samples = Samples(m, magnitude, telemetry, names, field)
    return SyntheticCase(np.arange(n_samples, dtype=float), samples, truth, noise_ut, field)


CAP_TRUTH = Springmann(1.02, 0.98, 1.05, -3.0, 5.0, 8.0, 0.01, -0.02, 0.015)
"""The sensor of the one-sided coverage cases (docs/adr/0026)."""


def constant_field_cap(
    cap_deg: float, n_samples: int = 5000, *, noise_ut: float = 0.2, field_ut: float = 47.0,
    seed: int = 1,
) -> SyntheticCase:  # fmt: skip
    """Field directions uniform within ``cap_deg`` of -z (90: a uniform hemisphere), |h| constant:
    a sensor turned by hand in the Earth's field, one side only. Magnitude only (no vector)."""
    rng = np.random.default_rng(seed)
    z = -rng.uniform(np.cos(np.radians(cap_deg)), 1.0, n_samples)
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n_samples)
    r = np.sqrt(1.0 - z**2)
    field = field_ut * np.column_stack([r * np.cos(azimuth), r * np.sin(azimuth), z])
    truth = Calibration.from_springmann(CAP_TRUTH)
    m = truth.predict(field) + noise_ut * rng.standard_normal((n_samples, 3))
    samples = Samples.build(m, field_magnitude_ut=np.full(n_samples, field_ut))
    return SyntheticCase(np.arange(n_samples, dtype=float), samples, truth, noise_ut, field)


TRMM_BIAS_UT = np.array([5.0, 3.0, 6.0])
TRMM_D = np.array([[0.05, 0.05, 0.05], [0.05, 0.10, 0.05], [0.05, 0.05, 0.05]])
"""Crassidis, Lai and Harman's Table 1 truth: ``B = (I + D)^-1 (H + b)`` (50, 30, 60 mG)."""


def trmm_like(field_body_ut: Array, *, noise_ut: float = 0.05, seed: int = 3) -> SyntheticCase:
    """Crassidis, Lai and Harman's real-time paper scenario on a body-frame field along the orbit
    (``rig.steps.orbit.circular_orbit_track``: 402 km, 35 deg, Earth pointing, IGRF, a sample
    every 10 s for 8 h; |B| 19.6-42.6 uT): their truth ``T = (I + D)^-1``, offset
    ``(I + D)^-1 b``, raw noise ``noise_ut`` per axis (0.5 mG). Magnitude only (no vector)."""
    field = np.asarray(field_body_ut, float)
    t_matrix = np.linalg.inv(np.eye(3) + TRMM_D)
    truth = Calibration.from_t_matrix(t_matrix, t_matrix @ TRMM_BIAS_UT)
    truth = Calibration(truth.sensor, truth.offset_ut, truth.k_ut_per_unit)  # |h| only: no R
    n = field.shape[0]
    m = field @ t_matrix.T + t_matrix @ TRMM_BIAS_UT
    m = m + noise_ut * np.random.default_rng(seed).standard_normal((n, 3))
    samples = Samples.build(m, field_magnitude_ut=np.linalg.norm(field, axis=1))
    return SyntheticCase(10.0 * np.arange(n, dtype=float), samples, truth, noise_ut, field)


DELAY_K_UT_PER_A = np.array([[0.8, -0.5, 1.2], [-1.5, 0.4, 0.9]])
DELAY_SENSOR = np.array([[1.02, 0, 0], [0.01, 0.98, 0], [-0.02, 0.015, 1.01]])
DELAY_OFFSET_UT = np.array([3.0, -2.0, 5.0])
CURRENTS = ("smooth", "steps at random times", "steps on the sample grid")
"""How :func:`delayed_currents` makes its two harness currents."""


def delayed_currents(
    n_samples: int = 3000, *, seed: int = 1, rate_hz: float = 20.0, noise_ut: float = 0.05,
    currents: str = "smooth", delays_s: tuple[float, float] = (0.35, -0.12),
) -> SyntheticCase:  # fmt: skip
    """A cage run at ``rate_hz`` whose two harness currents reach the DUT ``delays_s`` late: the
    field steps through 40 uT directions every 100 samples; the currents (``CURRENTS``) are smooth
    (sinusoids and a ramp), or hold levels of 0-3 A for 0.25-2.25 s and step at random times (the
    telemetry column is the current at the sample times) or at sample times. The DUT at ``t``
    sees the currents at ``t - tau``; ``profiled_truth`` holds ``delay[i_a]``, ``delay[i_b]``."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) / rate_hz
    dirs = rng.standard_normal((n_samples // 100 + 1, 3))
    h = np.repeat(40.0 * dirs / np.linalg.norm(dirs, axis=1)[:, None], 100, axis=0)[:n_samples]
    if currents == "smooth":
        u = np.column_stack([1.0 + np.sin(2 * np.pi * t / 7.3) + 0.3 * np.sin(2 * np.pi * t / 1.9),
                             0.8 * np.cos(2 * np.pi * t / 5.1) + 0.02 * t])  # fmt: skip
        late = np.column_stack([np.interp(t - d, t, u[:, j]) for j, d in enumerate(delays_s)])
    elif currents in CURRENTS:
        on_grid = currents == "steps on the sample grid"
        u, late = _step_currents(rng, t, delays_s, on_grid)
    else:
        raise ValueError(f"currents: one of {CURRENTS}, not {currents!r}")
    channels = ("i_a", "i_b")
    truth = Calibration(DELAY_SENSOR, DELAY_OFFSET_UT, DELAY_K_UT_PER_A, channels)
    m = h @ DELAY_SENSOR.T + DELAY_OFFSET_UT + late @ DELAY_K_UT_PER_A
    m = m + noise_ut * rng.standard_normal((n_samples, 3))
    samples = Samples.build(m, field_ut=h, telemetry=u, channels=channels)
    truths = tuple((f"delay[{c}]", float(d)) for c, d in zip(channels, delays_s, strict=True))
    return SyntheticCase(t, samples, truth, noise_ut, h, profiled_truth=truths)


def _step_currents(
    rng: np.random.Generator, t: Array, delays_s: tuple[float, ...], on_grid: bool
) -> tuple[Array, Array]:
    """Per channel: the current at the sample times ``t`` (the telemetry) and at ``t - delay``
    (what the DUT sees); levels 0-3 A held 0.25-2.25 s, steps at random times (``on_grid``: at
    sample times)."""
    dt = float(t[1] - t[0])
    recorded, late = [], []
    for delay in delays_s:
        holds = rng.uniform(0.25, 2.25, size=int(t[-1] / 0.25) + 2)
        starts = t[0] - 1.0 + np.cumsum(holds)
        if on_grid:
            starts = t[0] + dt * np.ceil((starts - t[0]) / dt)
        levels = rng.integers(0, 4, size=starts.size + 1).astype(float)
        # the level held at a time: the one after the last step at or before it (a step at a
        # sample time, to rounding, is seen by that sample)
        recorded.append(levels[np.searchsorted(starts, t + 1e-6 * dt, side="right")])
        late.append(levels[np.searchsorted(starts, t - delay + 1e-6 * dt, side="right")])
    return np.column_stack(recorded), np.column_stack(late)


THERMAL_OFFSET_PER_K = np.array([0.04, -0.025, 0.06])
"""Offset coefficients of :func:`thermal_soak` (uT/K per axis)."""
THERMAL_SCALE_PER_K = 300e-6
"""Scale coefficient of :func:`thermal_soak` (1/K)."""


def thermal_soak(n_samples: int = 4000, *, seed: int = 1, noise_ut: float = 0.05) -> SyntheticCase:
    """A sphere of field directions (20-50 uT) recorded while the DUT warms from 10 to 40 C
    (0.2 K jitter): ``m = (1 + s_T dT) L h + o + o_T dT`` about the mean temperature."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n_samples, 3))
    h = u / np.linalg.norm(u, axis=1)[:, None] * rng.uniform(20.0, 50.0, (n_samples, 1))
    temp_c = np.linspace(10.0, 40.0, n_samples) + 0.2 * rng.standard_normal(n_samples)
    d_t = temp_c - temp_c.mean()
    gain = 1 + THERMAL_SCALE_PER_K * d_t
    m = gain[:, None] * (h @ DELAY_SENSOR.T) + DELAY_OFFSET_UT + np.outer(d_t, THERMAL_OFFSET_PER_K)
    m += noise_ut * rng.standard_normal((n_samples, 3))
    truth = Calibration(DELAY_SENSOR, DELAY_OFFSET_UT, THERMAL_OFFSET_PER_K[None, :],
                        ("temperature",))  # fmt: skip
    return SyntheticCase(np.arange(n_samples, dtype=float), Samples.build(m, field_ut=h), truth,
                         noise_ut, h, temperature=temp_c,
                         profiled_truth=(("scale per kelvin", THERMAL_SCALE_PER_K),))  # fmt: skip
