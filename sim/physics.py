"""Physics of the simulated cage: supplies, coils, polarity relays, load currents, ambient field
and magnetometers with hidden truth.

Everything is evaluated lazily at the clock's time (:func:`now_s`, :mod:`timebase`: the wall clock's
monotonic seconds, or simulated time), so protocol servers running in other threads see one
consistent, continuously evolving cage. The DUT model is the project's measurement
model (ARCHITECTURE.md, contract)::

    m(t) = (1 + s_T dT) L R h(t) + o + o_T dT + sum_j k_j u_j(t - tau_j) + n(t),
    h = K(r) G(t) I(t) + B_ambient(r, t),   dT = T(t) - T_ref

at the magnetometer's position ``r``: ``K(r)`` the coils' field per ampere there (``K`` at the
centre, shaped by Biot-Savart of the coil pairs, :mod:`sim.coils`), ``G(t)`` the coil supplies'
gains (an error, a drift in time and with the lab's temperature: the current the supply reports
stays the one it was set to) and ``B_ambient`` the lab field there (:mod:`sim.lab_field`).

with the DUT's temperature ``T`` a first-order thermal mass warmed by a heater load channel
(``[thermal]`` of the configuration; constant at 25 C without one).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

import timebase
from sim.coils import CageCoils, CoilPair
from sim.config import MagnetometerConfig, SimConfig, SimConfigError, SupplyConfig
from sim.lab_field import LabField
from sim.offset_wander import OffsetWander, WanderSpec
from sim.perming import Perming
from sim.sensor_response import SensorResponse
from sim.thermal_hysteresis import ThermalHysteresis
from sim.waveforms import FirstOrderSignal

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class RidenSpec:
    """A Riden RD60xx model as the published tables give it (docs/devices.md names them).

    ``a_per_count`` and ``i_max_a`` have one entry per current range: register 20 selects it on
    the RD6012P (0 = 6 A at 0.1 mA, 1 = 12 A at 1 mA); the other models have one range.
    """

    name: str
    v_per_count: float
    w_per_count: float
    a_per_count: tuple[float, ...]
    i_max_a: tuple[float, ...]
    v_max_v: float = 60.0


RIDEN_MODELS: dict[range, RidenSpec] = {
    range(60060, 60065): RidenSpec("RD6006", 0.01, 0.01, (0.001,), (6.0,)),
    range(60065, 60066): RidenSpec("RD6006P", 0.001, 0.001, (0.0001,), (6.0,)),
    range(60066, 60067): RidenSpec("RK6006", 0.01, 0.01, (0.001,), (6.0,)),
    range(60120, 60125): RidenSpec("RD6012", 0.01, 0.01, (0.01,), (12.0,)),
    range(60125, 60130): RidenSpec("RD6012P", 0.001, 0.001, (0.0001, 0.001), (6.0, 12.0)),
    range(60180, 60190): RidenSpec("RD6018", 0.01, 0.01, (0.01,), (18.0,)),
    range(60240, 60245): RidenSpec("RD6024", 0.01, 0.01, (0.01,), (24.0,)),
    range(60300, 60305): RidenSpec("RD6030", 0.01, 0.01, (0.01,), (30.0,)),
}


def riden_model(model_id: int) -> RidenSpec:
    """The Riden model of a model ID (register 0); ValueError for one no table lists."""
    for ids, spec in RIDEN_MODELS.items():
        if model_id in ids:
            return spec
    known = ", ".join(f"{s.name} {r.start}-{r.stop - 1}" for r, s in RIDEN_MODELS.items())
    raise ValueError(f"unknown Riden model id {model_id}; known: {known}")


def now_s() -> float:
    """The simulator's clock: ``timebase.monotonic()`` (s; simulated time inside
    ``timebase.simulated()``)."""
    return timebase.monotonic()


@dataclass
class Faults:
    """Faults on demand for one device (set by tests or the operator; read by its server)."""

    reply_delay_s: float = 0.0
    silent: bool = False  # no reply at all (timeout)
    drop_rate: float = 0.0  # probability of dropping a reply byte stream
    corrupt_rate: float = 0.0  # probability of flipping a byte in a reply
    exception_code: int = 0  # Modbus exception returned for every request (0 = none)
    disconnect: bool = False  # close connections / stop talking
    stuck: bool = False  # sensor repeats its last reading


class Supply:
    """A DC supply channel: CV/CC into a resistive (and for coils inductive) load.

    Set-points and limits are in V and A; the output current relaxes with the load's time constant.
    Over-voltage, over-current and (where the instrument has one, ``opp_w`` not None)
    over-power protection turn the output off and latch ``protection`` (1 OVP, 2 OCP, 3 OPP)
    until the output is enabled again.
    """

    def __init__(self, cfg: SupplyConfig, resistance_ohm: float, tau_s: float, v_max: float,
                 i_max: float) -> None:  # fmt: skip
        self.cfg = cfg
        self.name = cfg.name
        self.resistance_ohm = resistance_ohm
        self.v_max, self.i_max = v_max, i_max
        self.v_set = 0.0
        self.i_set = 0.0
        self.ovp_v = v_max * 1.1
        self.ocp_a = i_max * 1.1
        self.opp_w: float | None = None
        self.output = False
        self.protection = 0
        self.current = FirstOrderSignal(tau_s)
        self.faults = Faults()
        self.lock = timebase.RLock()
        self.writes = 0
        self.on_change: Callable[[float, float], None] | None = None
        """Told (time s, target current A) whenever the output's target changes (a heater)."""
        self.off_since_s: float | None = None
        """When (the simulator's clock, s) the output last went from on to off: by a command or
        a protection trip; None while it is on or was never on. What a test of a time to safe
        reads, on the supply's side."""

    def _target(self) -> float:
        if not self.output:
            return 0.0
        return min(self.v_set / self.resistance_ohm, self.i_set)

    def _target_power_w(self) -> float:
        """The power (W) the output settles at: I^2 R of its target current."""
        return self._target() ** 2 * self.resistance_ohm

    def cc_mode(self) -> bool:
        """True when the current limit, not the voltage, sets the output."""
        with self.lock:
            return self.output and self.v_set / self.resistance_ohm > self.i_set

    def _update(self, t_s: float) -> None:
        if self.output and (self.v_set > self.ovp_v):
            self._trip(t_s, 1)
        elif self.output and self._target() > self.ocp_a:
            self._trip(t_s, 2)
        elif self.output and self.opp_w is not None and self._target_power_w() > self.opp_w:
            self._trip(t_s, 3)
        self.current.set_target(t_s, self._target())
        if self.on_change is not None:
            self.on_change(t_s, self._target())

    def _trip(self, t_s: float, code: int) -> None:
        if self.output:
            self.off_since_s = t_s
        self.output = False
        self.protection = code

    def set_voltage(self, volts: float, t_s: float | None = None) -> None:
        """Voltage set-point (V), 0 to ``v_max``."""
        if not 0.0 <= volts <= self.v_max:
            raise ValueError(f"{self.name}: {volts} V outside 0-{self.v_max} V")
        with self.lock:
            self.v_set = volts
            self.writes += 1
            self._update(now_s() if t_s is None else t_s)

    def set_current(self, amps: float, t_s: float | None = None) -> None:
        """Current limit (A), 0 to ``i_max``."""
        if not 0.0 <= amps <= self.i_max:
            raise ValueError(f"{self.name}: {amps} A outside 0-{self.i_max} A")
        with self.lock:
            self.i_set = amps
            self.writes += 1
            self._update(now_s() if t_s is None else t_s)

    def set_output(self, on: bool, t_s: float | None = None) -> None:
        """Output enable; enabling clears a latched protection."""
        with self.lock:
            t = now_s() if t_s is None else t_s
            if on:
                self.off_since_s = None
            elif self.output:
                self.off_since_s = t
            self.output = bool(on)
            if on:
                self.protection = 0
            self.writes += 1
            self._update(t)

    def set_protection(self, ovp_v: float | None = None, ocp_a: float | None = None,
                       t_s: float | None = None, opp_w: float | None = None) -> None:  # fmt: skip
        """New OVP (V), OCP (A) and/or OPP (W) levels; one below the live output trips it at
        once, as on the instrument (not at the next set-point write)."""
        with self.lock:
            if ovp_v is not None:
                self.ovp_v = ovp_v
            if ocp_a is not None:
                self.ocp_a = ocp_a
            if opp_w is not None:
                self.opp_w = opp_w
            self.writes += 1
            self._update(now_s() if t_s is None else t_s)

    def power_w(self, t_s: float | None = None) -> float:
        """Output power (W): output voltage times output current."""
        return self.output_voltage(t_s) * self.output_current(t_s)

    def trip(self, code: int = 2, t_s: float | None = None) -> None:
        """Fault on demand: a protection trip (1 OVP, 2 OCP, 3 OPP)."""
        with self.lock:
            self._trip(now_s() if t_s is None else t_s, code)
            self._update(now_s() if t_s is None else t_s)

    def output_current(self, t_s: float | None = None) -> float:
        """Actual output current (A) at ``t_s``."""
        return self.current.value(now_s() if t_s is None else t_s)

    def output_voltage(self, t_s: float | None = None) -> float:
        """Output voltage (V): ``I R``, capped at the set-point."""
        with self.lock:
            if not self.output:
                return 0.0
            return min(self.output_current(t_s) * self.resistance_ohm, self.v_set)


@dataclass
class PolarityRelays:
    """One H-bridge relay per coil axis: +1 or -1. Switching a live coil is a hot switch."""

    hot_switch_limit_a: float
    sign: list[int] = field(default_factory=lambda: [1, 1, 1])
    hot_switches: int = 0
    switches: list[int] = field(default_factory=lambda: [0, 0, 0])
    """How many times each axis's relay changed position."""
    faults: Faults = field(default_factory=Faults)


def springmann_matrix(scale: tuple[float, ...], nonorth_rad: tuple[float, ...]) -> Array:
    """Sensor matrix of Springmann and Cutler eqs. 5-7 (lower triangular)."""
    a, b, c = scale
    rho, phi, lam = nonorth_rad
    return np.array(
        [
            [a, 0.0, 0.0],
            [b * math.sin(rho), b * math.cos(rho), 0.0],
            [
                c * math.sin(lam),
                c * math.sin(phi) * math.cos(lam),
                c * math.cos(phi) * math.cos(lam),
            ],
        ]
    )


def rotation_matrix(rotvec_rad: Array) -> Array:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(rotvec_rad))
    if angle < 1e-12:
        return np.eye(3)
    k = rotvec_rad / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.asarray(np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * (kx @ kx))


class Magnetometer:
    """A magnetometer's truth: ``m = T h + o + sum_j k_j u_j(t - tau_j) + n`` (uT)."""

    def __init__(self, cfg: MagnetometerConfig, rng: np.random.Generator,
                 wander_seed: int = 0, start_s: float | None = None) -> None:  # fmt: skip
        self.cfg = cfg
        self.name = cfg.name
        self.sensor = springmann_matrix(cfg.scale, tuple(math.radians(v) for v in cfg.nonorth_deg))
        self.rotation = rotation_matrix(np.radians(np.array(cfg.mounting_deg)))
        self.t_matrix = self.sensor @ self.rotation
        self.turn = np.eye(3)
        """How the sensor is turned from its mounting (a rotation fixture), cage frame."""
        self.offset_ut = np.array(cfg.offset_ut)
        cross = 1e-6 * np.array(cfg.cross_field_ppm_per_ut, float)
        np.fill_diagonal(cross, 0.0)
        self.cross_field = cross if np.any(cross) else None
        """Per uT of field along another axis, the relative change of an axis's scale."""
        self.offset_ut_per_k = np.array(cfg.offset_ut_per_k)
        self.faults = Faults()
        self._rng = rng
        self._lock = timebase.Lock()
        self._last: Array | None = None
        self.wander = OffsetWander(WanderSpec(cfg.offset_drift_nt_per_h, cfg.offset_walk_nt_per_sqrt_h,
                                              cfg.offset_flicker_nt), wander_seed,
                                   now_s() if start_s is None else start_s)  # fmt: skip
        """The offset's wander over time (drift, random walk, flicker), from ``start_s`` (the
        cage's start, so one seed gives one wander whenever it starts)."""
        self.perming = Perming(cfg.perming_threshold_ut, cfg.perming_nt_per_ut)
        """What a strong field left in the offset (cleared by a set/reset pulse)."""
        self.hysteresis = ThermalHysteresis(cfg.offset_hysteresis_nt, cfg.hysteresis_band_k)
        self.response = SensorResponse(cfg.response_tau_s, cfg.response_integration_s)
        """What it reads of a changing field (a conversion window, a low-pass)."""
        self._hysteresis_ut = np.zeros(3)  # its offset at the latest reading's temperature

    def truth_reading(
        self, field_ut: Array, loads_a: dict[str, float], temperature_c: float | None = None
    ) -> Array:
        """Noise-free reading for a field (cage frame), delayed load currents (uT) and the
        sensor's temperature (C; None: at its reference temperature)."""
        d_t = 0.0 if temperature_c is None else temperature_c - self.cfg.temperature_ref_c
        u = self.rotation @ (self.turn.T @ field_ut)  # the field in the sensor's axes
        if self.cross_field is not None:
            u = u + u * (self.cross_field @ u)
        m = (1.0 + self.cfg.scale_per_k * d_t) * (self.sensor @ u)
        m = m + self.offset_ut + self.offset_ut_per_k * d_t + self.sensor @ self.perming.shift_ut
        m = m + self._hysteresis_ut
        for ch, k in self.cfg.k_ut_per_a.items():
            m = m + np.asarray(k) * loads_a.get(ch, 0.0)
        return np.asarray(m)

    def sensed_field(self, t_s: float, field_at: Callable[[float], Array]) -> Array:
        """The field (uT, cage frame) as the sensor's response passes it at ``t_s``: the field
        ``field_at(t)`` filtered (without noise: the caller adds it once)."""
        with self._lock:
            return self.response.reading(t_s, field_at)

    def set_turn(self, rotation: Array) -> None:
        """Turn the sensor on its fixture: ``rotation`` (cage frame) from its mounting (what an
        operator does when a procedure asks; tests play the operator)."""
        with self._lock:
            self.turn = np.array(rotation, float)

    def sample(
        self,
        field_ut: Array,
        loads_a: dict[str, float],
        temperature_c: float | None = None,
        t_s: float | None = None,
    ) -> Array:
        """One noisy reading (uT) at ``t_s`` (the offset's wander then; None: none); a stuck
        sensor repeats its last one."""
        with self._lock:
            if self.faults.stuck and self._last is not None:
                return self._last.copy()
            noise = self.cfg.noise_ut * self._rng.standard_normal(3)
            self.perming.expose(self.rotation @ (self.turn.T @ field_ut))
            if temperature_c is not None and self.hysteresis.active:
                self._hysteresis_ut = self.hysteresis.offset_ut(temperature_c)
            self._last = self.truth_reading(field_ut, loads_a, temperature_c) + noise
            if t_s is not None and self.wander.spec.active:
                self._last = self._last + self.wander.value(t_s)
            return self._last.copy()


_CENTRE = np.zeros((1, 3))
"""The cage's centre as a (1, 3) array of positions (m)."""


class CagePhysics:
    """The cage: supplies drive coils through polarity relays; loads bias the magnetometers."""

    def __init__(self, cfg: SimConfig, start_s: float | None = None) -> None:
        self.cfg = cfg
        self.rng = np.random.default_rng(cfg.seed)
        self.start_s = now_s() if start_s is None else start_s
        """The simulator's start (its clock; default now): the lab field's and the gains' time
        origin, so one seed gives one lab field from the start whenever it starts."""
        self.coil_matrix = np.array(cfg.cage.coil_matrix_ut_per_a)
        self.lab = LabField(cfg.ambient, cfg.seed)
        c = cfg.cage
        self.coils = None if c.coil_shape is None else CageCoils(
            tuple(CoilPair(c.coil_shape, c.coil_size_m[j], c.coil_spacing_m[j]) for j in range(3)),
            self.coil_matrix,
        )  # fmt: skip
        self.supplies: dict[str, Supply] = {}
        self.coil_supply: list[Supply] = [None, None, None]  # type: ignore[list-item]
        self.trim_supply: list[Supply | None] = [None, None, None]
        self._open_supplies(cfg)
        self.relays = PolarityRelays(cfg.cage.hot_switch_limit_a)
        self.bipolar_sign = [1, 1, 1]
        self.magnetometers = {
            m.name: Magnetometer(
                m, np.random.default_rng([cfg.seed, i]), 1000 * cfg.seed + i, self.start_s
            )
            for i, m in enumerate(cfg.magnetometers)
        }
        self.position_m = {m.name: tuple(m.position_m) for m in cfg.magnetometers}
        """Per magnetometer, where it sits (m from the centre, cage frame)."""
        self.coil_matrix_at = {
            m.name: self.coil_matrix_at_m(m.position_m) for m in cfg.magnetometers
        }
        """Per magnetometer, the coils' field per ampere (uT/A) at its position."""
        ph = np.random.default_rng([cfg.seed, 99]).uniform(0, 2 * np.pi, size=6)
        self._drift_phase, self._ripple_phase = ph[:3], ph[3:]
        a = cfg.ambient  # its vectors as arrays once (a reading asks for them 50 times a second)
        self._ambient_ut = np.array(a.field_ut, float)
        self._drift_ut = np.array(a.drift_amplitude_ut, float)
        self._drift_rad_per_s = 2 * np.pi / np.array(a.drift_period_s, float)
        self._ripple_ut = np.array(a.ripple_amplitude_ut, float)
        self._ambient_rng = np.random.default_rng([cfg.seed, 100])
        self._ambient_rngs = {
            m.name: np.random.default_rng([cfg.seed, 100, i + 1])
            for i, m in enumerate(cfg.magnetometers)
        }
        """Per magnetometer, its own draws of the lab field's white noise: what one device reads
        does not depend on how often another was read before it (threads interleaving)."""
        self._lock = timebase.Lock()
        self.events: list[tuple[float, str]] = []
        thermal = cfg.thermal
        self.ambient_c = thermal.ambient_c if thermal is not None else 25.0
        self._warming = FirstOrderSignal(thermal.tau_s if thermal else 0.0)
        """The DUT's rise above ambient (K), relaxing towards ``k_per_w`` times the heater's power."""
        if thermal is not None:
            heater = self.supplies[thermal.heater]

            def heater_changed(t_s: float, amps: float) -> None:
                self._warming.set_target(t_s, thermal.k_per_w * amps**2 * heater.resistance_ohm)

            heater.on_change = heater_changed

    def _open_supplies(self, cfg: SimConfig) -> None:
        """Every supply and load channel; a bipolar cage needs bipolar coil supplies."""
        for s in cfg.supplies:
            if s.axis is not None:
                r = cfg.cage.resistance_ohm[s.axis]
                tau = cfg.cage.inductance_h[s.axis] / r
            else:
                r, tau = s.resistance_ohm, s.tau_s
            v_max, i_max = self._limits(s)
            supply = Supply(s, r, tau, v_max, i_max)
            self.supplies[s.name] = supply
            if s.axis is not None:
                self.coil_supply[s.axis] = supply
            if s.trim is not None:
                self.trim_supply[s.trim] = supply
        constants = np.linalg.norm(np.array(cfg.cage.coil_matrix_ut_per_a, float), axis=0)
        self._trim_scale = np.array(cfg.cage.trim_ut_per_a, float) / constants
        if cfg.cage.polarity == "bipolar":
            for s in cfg.supplies:
                if s.axis is not None and not (s.kind == "regmap" and self._bipolar(s)):
                    raise SimConfigError(
                        f"supply '{s.name}': cage.polarity = 'bipolar' needs a bipolar"
                        " register-map supply on every coil axis"
                    )

    @staticmethod
    def _bipolar(s: SupplyConfig) -> bool:
        from sim.regmap import load_regmap

        return load_regmap(s.regmap).bipolar

    @staticmethod
    def _limits(s: SupplyConfig) -> tuple[float, float]:
        if s.kind == "riden-rd60xx":
            try:
                riden = riden_model(s.model_id)
            except ValueError as exc:
                raise SimConfigError(f"supply '{s.name}': {exc}") from None
            if not 0 <= s.current_range < len(riden.i_max_a):
                raise SimConfigError(
                    f"supply '{s.name}': current_range {s.current_range} does not exist on the"
                    f" {riden.name}; use 0-{len(riden.i_max_a) - 1}"
                )
            return riden.v_max_v, max(riden.i_max_a)
        from sim.regmap import load_regmap

        spec = load_regmap(s.regmap)
        return spec.v_max, spec.i_max

    # --- polarity -------------------------------------------------------------------------------

    def set_polarity(self, axis: int, sign: int, t_s: float | None = None) -> None:
        """Flip the relay H-bridge of ``axis`` to ``sign`` (+1/-1). Hot switching trips the supply.

        Break-before-make: a real relay switching an inductive coil carrying current arcs; the
        simulator records a hot switch and trips that axis's supply (OCP) so the rig must bring the
        current to zero first.
        """
        t = now_s() if t_s is None else t_s
        sign = 1 if sign >= 0 else -1
        if sign == self.relays.sign[axis]:
            return
        supply = self.coil_supply[axis]
        live = abs(supply.output_current(t))
        if live > self.relays.hot_switch_limit_a:
            self.relays.hot_switches += 1
            self.events.append((t, f"hot switch on axis {'xyz'[axis]} at {live:.3f} A"))
            supply.trip(2, t)
        self.relays.sign[axis] = sign
        self.relays.switches[axis] += 1

    def set_bipolar_sign(self, axis: int, sign: int, t_s: float | None = None) -> None:
        """Output polarity of a four-quadrant supply: the current reverses through zero.

        The supply's own current signal is unsigned, so a sign change restarts it from the mirrored
        value: the coil current passes continuously through zero with the coil's time constant.
        """
        t = now_s() if t_s is None else t_s
        sign = 1 if sign >= 0 else -1
        if sign == self.bipolar_sign[axis]:
            return
        supply = self.coil_supply[axis]
        present = supply.output_current(t)
        self.bipolar_sign[axis] = sign
        supply.current.jump(t, -present)
        with supply.lock:
            supply.current.set_target(t, supply._target())

    # --- field ----------------------------------------------------------------------------------

    def coil_matrix_at_m(self, position_m: tuple[float, ...] | Array) -> Array:
        """The coils' field per ampere (uT/A, 3x3) at ``position_m`` (m from the centre)."""
        if self.coils is None:
            return self.coil_matrix.copy()
        return self.coils.matrix_at(np.asarray(position_m, float))

    def move(self, name: str, position_m: tuple[float, ...]) -> None:
        """Move magnetometer ``name`` to ``position_m`` (m from the centre: what an operator does
        when a field map asks; tests play the operator)."""
        self.coil_matrix_at[name] = self.coil_matrix_at_m(position_m)
        self.position_m[name] = tuple(float(v) for v in position_m)

    def coil_gains(self, t_s: float | None = None) -> Array:
        """Per coil axis, the current flowing per ampere the supply reports (its gain error, its
        drift since the start and with the lab's temperature)."""
        t = (now_s() if t_s is None else t_s) - self.start_s
        lab_k = self.lab.lab_temperature_c(t)
        ppm = [s.cfg.gain_ppm + s.cfg.gain_drift_ppm_per_h * t / 3600.0 + s.cfg.gain_ppm_per_k * lab_k
               for s in self.coil_supply]  # fmt: skip
        return 1.0 + 1e-6 * np.array(ppm)

    def coil_currents(self, t_s: float | None = None) -> Array:
        """Signed coil currents (A) as the supplies report them, polarity included."""
        t = now_s() if t_s is None else t_s
        signs = self.relays.sign if self.cfg.cage.polarity == "relay" else self.bipolar_sign
        return np.array([signs[i] * self.coil_supply[i].output_current(t) for i in range(3)])

    def true_coil_currents(self, t_s: float | None = None) -> Array:
        """Signed coil currents (A) that flow: the reported ones times the supplies' gains, plus
        each trim winding's current as the coil current that makes its field (the trim's field
        per ampere over the coil's)."""
        t = now_s() if t_s is None else t_s
        trims = self._trim_scale * self.trim_currents(t)
        return np.asarray(self.coil_currents(t) * self.coil_gains(t) + trims)

    def trim_currents(self, t_s: float | None = None) -> Array:
        """Currents (A) in the trim windings (zeros without them)."""
        t = now_s() if t_s is None else t_s
        return np.array([0.0 if s is None else s.output_current(t) for s in self.trim_supply])

    def ambient_ut(
        self,
        t_s: float,
        noise: bool = True,
        position_m: tuple[float, ...] | None = None,
        seen_by: str | None = None,
    ) -> Array:
        """Lab field (uT) at ``position_m`` (default: the centre): constant, drift, mains ripple,
        the lab field's daily, 1/f, gradient and traffic terms and (optionally) white noise, as
        magnetometer ``seen_by`` sees it (its own noise draws; None: the cage's)."""
        since = t_s - self.start_s
        where = _CENTRE if position_m is None else np.asarray([position_m], float)
        b = self._ambient_ut + self._drift_ut * np.sin(
            since * self._drift_rad_per_s + self._drift_phase
        )
        b = b + self.mains_ripple_ut(t_s)
        b = b + self.lab.uniform_ut(since) + self.lab.local_ut(since, where)[0]
        if noise:
            b = b + self.ambient_noise_ut(seen_by)
        return np.asarray(b)

    def ambient_noise_ut(self, seen_by: str | None = None) -> Array:
        """One draw of the lab field's white noise (uT), from magnetometer ``seen_by``'s own
        draws (None: the cage's)."""
        a = self.cfg.ambient
        if a.noise_ut <= 0:
            return np.zeros(3)
        rng = self._ambient_rng if seen_by is None else self._ambient_rngs[seen_by]
        with self._lock:
            return np.asarray(a.noise_ut * rng.standard_normal(3))

    def mains_ripple_ut(self, t_s: float) -> Array:
        """The lab field's mains ripple at ``t_s`` (uT, the same everywhere)."""
        a = self.cfg.ambient
        since = t_s - self.start_s
        return np.asarray(
            self._ripple_ut * np.sin(2 * np.pi * a.ripple_hz * since + self._ripple_phase)
        )

    def field_ut(self, t_s: float | None = None, noise: bool = True) -> Array:
        """True field at the centre (the DUT's place) in the cage frame: ``K G I + B_ambient``."""
        t = now_s() if t_s is None else t_s
        return np.asarray(self.coil_matrix @ self.true_coil_currents(t) + self.ambient_ut(t, noise))

    def field_at_ut(self, name: str, t_s: float | None = None, noise: bool = True) -> Array:
        """True field (uT, cage frame) where magnetometer ``name`` sits."""
        t = now_s() if t_s is None else t_s
        position = self.position_m[name]
        coils = self.coil_matrix_at[name] @ self.true_coil_currents(t)
        return np.asarray(coils + self.ambient_ut(t, noise, position, name))

    def load_currents(
        self, t_s: float, delays_s: dict[str, float] | None = None
    ) -> dict[str, float]:
        """Load-channel currents (A), each at ``t - tau_j``."""
        delays = delays_s or {}
        return {
            name: s.output_current(t_s - delays.get(name, 0.0))
            for name, s in self.supplies.items()
            if s.cfg.axis is None and s.cfg.trim is None
        }

    def dut_temperature_c(self, t_s: float | None = None) -> float:
        """The DUT's temperature (C): ambient plus the heater's warming. Every magnetometer is at
        the DUT position and shares it (a reference has no temperature coefficients)."""
        return self.ambient_c + self._warming.value(now_s() if t_s is None else t_s)

    def read_magnetometer(self, name: str, t_s: float | None = None) -> Array:
        """One noisy reading of a magnetometer (uT, its own frame, before quantization)."""
        t = now_s() if t_s is None else t_s
        mag = self.magnetometers[name]
        if mag.response.active:  # what it senses of the field's recent past, plus this noise
            field = mag.sensed_field(t, lambda s: self.field_at_ut(name, s, noise=False))
            field = field + self.ambient_noise_ut(name)
        else:
            field = self.field_at_ut(name, t)
        return mag.sample(field, self.load_currents(t, mag.cfg.delay_s),
                          self.dut_temperature_c(t), t)  # fmt: skip

    def safe(self) -> None:
        """Turn every output off (the simulator's own emergency stop)."""
        for s in self.supplies.values():
            s.set_output(False)
