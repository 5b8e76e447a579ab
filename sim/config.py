"""The simulated cage's configuration: every physical parameter, read from a TOML file.

The file is the single source of truth (the hidden DUT parameters included: tests may read them,
the rig never does). ``seed`` drives every random draw, so a file always gives the same cage.
"""

from __future__ import annotations

import difflib
import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

DEFAULT_CONFIG = Path(__file__).with_name("default_cage.toml")


class SimConfigError(ValueError):
    """The simulator configuration file is malformed (message names the key and the fix)."""


def _vec(d: dict[str, Any], key: str, where: str, n: int = 3) -> tuple[float, ...]:
    value = d.get(key)
    if not isinstance(value, list) or len(value) != n:
        raise SimConfigError(f"{where}.{key} must be a list of {n} numbers")
    return tuple(float(v) for v in value)


def _mat(d: dict[str, Any], key: str, where: str) -> tuple[tuple[float, ...], ...]:
    value = d.get(key)
    if not isinstance(value, list) or len(value) != 3:
        raise SimConfigError(f"{where}.{key} must be a 3x3 list of lists")
    return tuple(_vec({"r": row}, "r", f"{where}.{key}") for row in value)


@dataclass(frozen=True)
class CageConfig:
    """Coils: field at the centre = coil_matrix @ currents + ambient; over the volume shaped by
    the coil pairs' geometry (``coil_shape`` "square" or "circular", side or diameter
    ``coil_size_m`` and plane spacing ``coil_spacing_m`` per axis; no shape: a uniform field)."""

    coil_matrix_ut_per_a: tuple[tuple[float, ...], ...]
    resistance_ohm: tuple[float, ...]
    inductance_h: tuple[float, ...]
    polarity: str  # "relay" (H-bridge relays per axis) or "bipolar"
    hot_switch_limit_a: float = 0.05
    coil_shape: str | None = None
    coil_size_m: tuple[float, ...] = (2.0, 2.0, 2.0)
    coil_spacing_m: tuple[float, ...] = (1.089, 1.089, 1.089)
    # trim windings: a few turns on each coil's frame, driven by their own supplies (``trim``):
    # field per ampere at the centre along their coil's axis (uT/A), shaped as the coil's field
    trim_ut_per_a: tuple[float, ...] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class AmbientConfig:
    """Lab field at the cage centre: constant + slow sinusoidal drift + mains ripple + white
    noise; and by position and time since start (``sim.lab_field``): a static gradient (uT/m), a
    daily variation, 1/f noise, traffic; the lab temperature's daily swing (K, the supplies')."""

    field_ut: tuple[float, ...]
    drift_amplitude_ut: tuple[float, ...] = (0.0, 0.0, 0.0)
    drift_period_s: tuple[float, ...] = (600.0, 900.0, 1200.0)
    ripple_amplitude_ut: tuple[float, ...] = (0.0, 0.0, 0.0)
    ripple_hz: float = 50.0
    noise_ut: float = 0.0
    gradient_ut_per_m: tuple[tuple[float, ...], ...] = ((0.0,) * 3,) * 3
    diurnal_amplitude_ut: tuple[float, ...] = (0.0, 0.0, 0.0)
    diurnal_period_s: float = 86400.0
    flicker_ut: float = 0.0  # rms of the 1/f noise per axis, 1e-5 to 1 Hz
    traffic_rate_per_h: float = 0.0
    traffic_field_ut: float = 0.02  # a vehicle's typical field at the cage centre
    traffic_distance_m: float = 30.0  # from the cage centre to the street (+y)
    traffic_duration_s: float = 300.0  # mean stay
    lab_temperature_swing_c: float = 0.0


@dataclass(frozen=True)
class EndpointConfig:
    """Where a device listens: Modbus TCP, Modbus RTU on a pty, a serial pty, or an I2C bus."""

    transport: str
    device_id: int = 1
    baudrate: int = 115200


@dataclass(frozen=True)
class SupplyConfig:
    """A coil supply or a load-current channel (a supply into a resistor, or an electronic load)."""

    name: str
    kind: str  # a supply kind of sim/device_kinds.py: "riden-rd60xx", "regmap"
    endpoint: EndpointConfig
    axis: int | None = None  # coil axis 0-2, None for a load channel
    trim: int | None = None  # the trim winding of coil axis 0-2 it drives (cage.trim_ut_per_a)
    model_id: int = 60125
    current_range: int = 0  # Riden RD6012P register 20: 0 = 6 A range (0.1 mA), 1 = 12 A (1 mA)
    regmap: str = ""
    resistance_ohm: float = 5.0
    tau_s: float = 0.002
    input_voltage_v: float = 48.0
    gain_ppm: float = 0.0  # coil supplies: output current / set current - 1, at the start
    gain_drift_ppm_per_h: float = 0.0  # ageing and warm-up, from the start
    gain_ppm_per_k: float = 0.0  # with the lab temperature (its daily swing)


@dataclass(frozen=True)
class RelayConfig:
    """Polarity relays (one H-bridge per axis) on a Modbus register-map device."""

    name: str
    regmap: str
    endpoint: EndpointConfig


@dataclass(frozen=True)
class MagnetometerConfig:
    """A magnetometer with its truth (Springmann-Cutler form, rad inside) at ``position_m`` (m
    from the cage centre, cage frame; the DUT's place is the centre)."""

    name: str
    kind: str  # a magnetometer kind of sim/device_kinds.py: "hmr2300", "ascii-mag", "rm3100", ...
    endpoint: EndpointConfig
    scale: tuple[float, ...] = (1.0, 1.0, 1.0)
    nonorth_deg: tuple[float, ...] = (0.0, 0.0, 0.0)  # rho, phi, lambda
    mounting_deg: tuple[float, ...] = (0.0, 0.0, 0.0)  # rotation vector, cage -> sensor frame
    offset_ut: tuple[float, ...] = (0.0, 0.0, 0.0)
    k_ut_per_a: dict[str, tuple[float, ...]] = field(default_factory=dict)
    delay_s: dict[str, float] = field(default_factory=dict)
    noise_ut: float = 0.0
    rate_hz: float = 20.0
    serial_number: str = "0001"
    i2c_address: int = 0x20
    line_format: str = "{x:.4f} {y:.4f} {z:.4f}"
    temperature_ref_c: float = 25.0  # the temperature its scale and offset refer to
    scale_per_k: float = 0.0  # common scale coefficient (1/K): m = (1 + s dT) T h + ...
    offset_ut_per_k: tuple[float, ...] = (0.0, 0.0, 0.0)  # offset coefficient (uT/K, per axis)
    position_m: tuple[float, ...] = (0.0, 0.0, 0.0)
    role: str | None = None  # "reference" (the cage's, inside) or "ambient" (outside the coils)
    # the certificate the rig is given (a reference's): its 1-sigma, and the error drawn within it
    # (seeded) -- scale (relative), axis angles and mounting (arcsec); zeros: an exact certificate
    certificate_scale_sigma: float = 0.0
    certificate_angle_sigma_arcsec: float = 0.0
    certificate_mounting_sigma_arcsec: float = 0.0
    # a scalar (total-field) sensor's own (kind "geometrics-cm201"): its optical axis (cage frame),
    # absolute offset, heading error (nT times the cosine of the field's angle to the axis) and
    # dead zones (degrees about the axis and about the plane normal to it)
    optical_axis: tuple[float, ...] = (0.0, 0.0, 1.0)
    scalar_offset_nt: float = 0.0
    heading_error_nt: float = 0.0
    dead_zone_deg: float = 10.0
    # how the offset wanders (sim.offset_wander): drift per axis (nT/h), random walk (nT/sqrt(h)),
    # flicker floor (nT: the Allan deviation's flat part)
    offset_drift_nt_per_h: tuple[float, ...] = (0.0, 0.0, 0.0)
    offset_walk_nt_per_sqrt_h: float = 0.0
    offset_flicker_nt: float = 0.0
    # cross-field effect (ppm of an axis's scale per uT of field along another, sensor frame;
    # rows the measured axis, the diagonal unused): m = L (u + u * (C u)), u = R h
    cross_field_ppm_per_ut: tuple[tuple[float, ...], ...] = ((0.0,) * 3,) * 3
    # perming (sim.perming): a field beyond the threshold (uT at the sensor) leaves an offset of
    # perming_nt_per_ut per uT beyond it, along that field, until a set/reset pulse (an AMR
    # sensor's; a device with automatic set/reset pulses before every reading); 0: none
    perming_threshold_ut: float = 0.0
    perming_nt_per_ut: float = 0.0
    # thermal hysteresis (sim.thermal_hysteresis): the offset on warming less that on cooling at
    # the same temperature (nT per axis), reached over 2 hysteresis_band_k after a reversal
    offset_hysteresis_nt: tuple[float, ...] = (0.0, 0.0, 0.0)
    hysteresis_band_k: float = 1.0
    # the response to a changing field (sim.sensor_response): a conversion window (s, a boxcar
    # before each reading's date) and a first-order low-pass (s); 0: the instantaneous field
    response_integration_s: float = 0.0
    response_tau_s: float = 0.0


@dataclass(frozen=True)
class ThermalConfig:
    """The DUT's temperature: a first-order thermal mass warmed by a heater on its mount,
    ``tau dT/dt = ambient + k P - T`` with ``P = I^2 R`` of the heater's load channel."""

    heater: str  # a load channel (a supply into the heater's resistance)
    ambient_c: float = 25.0
    k_per_w: float = 1.0  # steady-state rise per watt of heater power (K/W)
    tau_s: float = 60.0  # thermal time constant of the DUT and its mount (s)


@dataclass(frozen=True)
class ThermometerConfig:
    """A Modbus temperature module reading the DUT's temperature (register-map device)."""

    name: str
    regmap: str
    endpoint: EndpointConfig


@dataclass(frozen=True)
class SimConfig:
    """The whole simulated cage."""

    seed: int
    cage: CageConfig
    ambient: AmbientConfig
    supplies: tuple[SupplyConfig, ...]
    relay: RelayConfig | None
    magnetometers: tuple[MagnetometerConfig, ...]
    source: str = ""
    faults: dict[str, dict[str, float | bool | int]] = field(default_factory=dict)
    """Faults active from the start, per device name (fields of ``sim.physics.Faults``)."""
    thermal: ThermalConfig | None = None
    """The DUT's thermal model (None: the DUT stays at 25 C, its reference temperature)."""
    thermometer: ThermometerConfig | None = None

    def supply(self, name: str) -> SupplyConfig:
        """A supply or load channel by name."""
        for s in self.supplies:
            if s.name == name:
                return s
        raise KeyError(name)

    def magnetometer(self, name: str) -> MagnetometerConfig:
        """A magnetometer by name."""
        for m in self.magnetometers:
            if m.name == name:
                return m
        raise KeyError(name)


AXES = {"x": 0, "y": 1, "z": 2}


def _endpoint(d: dict[str, Any], where: str) -> EndpointConfig:
    transport = d.get("transport")
    allowed = ("modbus-tcp", "modbus-rtu", "serial", "i2c")
    if transport not in allowed:
        raise SimConfigError(f"{where}.transport must be one of {', '.join(allowed)}")
    return EndpointConfig(
        str(transport), int(d.get("device_id", 1)), int(d.get("baudrate", 115200))
    )


ENDPOINT_KEYS = ("transport", "device_id", "baudrate")
"""The keys of a device table that make its :class:`EndpointConfig`."""


def _keys_of(cls: type) -> tuple[str, ...]:
    """The keys a table of ``cls`` may hold: its fields (an ``endpoint`` as its own keys)."""
    names = tuple(f.name for f in fields(cls) if f.name != "endpoint")
    return names + (ENDPOINT_KEYS if "endpoint" in {f.name for f in fields(cls)} else ())


TABLE_KEYS: dict[str, tuple[str, ...]] = {
    "cage": _keys_of(CageConfig),
    "ambient": _keys_of(AmbientConfig),
    "supplies": _keys_of(SupplyConfig),
    "relay": _keys_of(RelayConfig),
    "magnetometers": _keys_of(MagnetometerConfig),
    "thermal": _keys_of(ThermalConfig),
    "thermometer": _keys_of(ThermometerConfig),
}
"""Every key each table (or each entry of an array of tables) may hold, from the dataclasses."""
TOP_KEYS = ("seed", *TABLE_KEYS, "faults")
"""The top-level keys of a simulator configuration."""


def _unknown(where: str, key: str, valid: tuple[str, ...]) -> SimConfigError:
    match = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
    fix = f"did you mean '{match[0]}'?" if match else f"valid keys: {', '.join(valid)}"
    return SimConfigError(f"{where}: unknown key '{key}'; {fix}")


def _check_keys(raw: dict[str, Any]) -> None:
    """Refuse a key no table has, naming it and the nearest valid one (a misspelt key was
    silently ignored and its default used, issue 51)."""
    for key in raw:
        if key not in TOP_KEYS:
            raise _unknown("the top level", key, TOP_KEYS)
    for name, valid in TABLE_KEYS.items():
        value = raw.get(name)
        entries = value if isinstance(value, list) else [value] if value is not None else []
        for i, table in enumerate(entries):
            where = f"{name}[{i}]" if isinstance(value, list) else name
            if not isinstance(table, dict):
                raise SimConfigError(f"{where} must be a table")
            for key in table:
                if key not in valid:
                    raise _unknown(where, key, valid)


def _check_finite(raw: dict[str, Any]) -> None:
    """Refuse NaN, infinity and integers beyond a float anywhere in the file, naming the key
    (a NaN was an internal error of the physics, issue 51). Walks the document without recursion."""
    stack: list[tuple[str, Any]] = [("", raw)]
    while stack:
        where, value = stack.pop()
        if isinstance(value, dict):
            stack.extend((f"{where}.{k}" if where else str(k), v) for k, v in value.items())
        elif isinstance(value, list):
            stack.extend((f"{where}[{i}]", v) for i, v in enumerate(value))
        elif isinstance(value, float) and not math.isfinite(value):
            raise SimConfigError(f"{where} is {value}: write a finite number")
        elif isinstance(value, int) and not isinstance(value, bool) and abs(value) > 2**63:
            raise SimConfigError(f"{where} is {str(value)[:20]}...: write a number of sane size")


def load_config(path: str | Path = DEFAULT_CONFIG) -> SimConfig:
    """Parse and validate a simulator TOML file: unknown keys (with the nearest valid one) and
    numbers that are not finite are refused, naming the key."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SimConfigError(f"{path}: no such simulator configuration file") from None
    except tomllib.TOMLDecodeError as exc:
        raise SimConfigError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise SimConfigError(f"{path}: arrays or tables nested too deep; flatten them") from None
    try:
        _check_keys(raw)
        _check_finite(raw)
        return _parse(raw, str(path))
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, SimConfigError):
            raise SimConfigError(f"{path}: {exc}") from None
        raise SimConfigError(f"{path}: missing or malformed entry {exc}") from None


def _cage(c: dict[str, Any]) -> CageConfig:
    cage = CageConfig(
        coil_matrix_ut_per_a=_mat(c, "coil_matrix_ut_per_a", "cage"),
        resistance_ohm=_vec(c, "resistance_ohm", "cage"),
        inductance_h=_vec(c, "inductance_h", "cage"),
        polarity=str(c.get("polarity", "relay")),
        hot_switch_limit_a=float(c.get("hot_switch_limit_a", 0.05)),
        trim_ut_per_a=_vec_or(c, "trim_ut_per_a", "cage", (0.0, 0.0, 0.0)),
        **_geometry(c),
    )
    if cage.polarity not in ("relay", "bipolar"):
        raise SimConfigError("cage.polarity must be 'relay' or 'bipolar'")
    return cage


HELMHOLTZ_SPACING = {"square": 0.5445, "circular": 0.5}
"""Plane spacing per unit side (square) or diameter (circular) of the most uniform pair (square:
0.5445 a, where the second derivative at the centre vanishes; circular: the radius)."""


def _geometry(c: dict[str, Any]) -> dict[str, Any]:
    shape = c.get("coil_shape")
    if shape is None:
        return {}
    if shape not in HELMHOLTZ_SPACING:
        raise SimConfigError("cage.coil_shape must be 'square' or 'circular' (or absent: uniform)")
    size = _vec(c, "coil_size_m", "cage")
    spacing = _vec_or(
        c, "coil_spacing_m", "cage", tuple(HELMHOLTZ_SPACING[shape] * v for v in size)
    )
    if min(size) <= 0 or min(spacing) <= 0:
        raise SimConfigError("cage.coil_size_m and cage.coil_spacing_m must be positive")
    return {"coil_shape": str(shape), "coil_size_m": size, "coil_spacing_m": spacing}


def _ambient(a: dict[str, Any]) -> AmbientConfig:
    return AmbientConfig(
        field_ut=_vec(a, "field_ut", "ambient"),
        drift_amplitude_ut=_vec(a, "drift_amplitude_ut", "ambient"),
        drift_period_s=_vec(a, "drift_period_s", "ambient"),
        ripple_amplitude_ut=_vec(a, "ripple_amplitude_ut", "ambient"),
        ripple_hz=float(a.get("ripple_hz", 50.0)),
        noise_ut=float(a.get("noise_ut", 0.0)),
        gradient_ut_per_m=_mat(a, "gradient_ut_per_m", "ambient")
        if "gradient_ut_per_m" in a
        else ((0.0,) * 3,) * 3,
        diurnal_amplitude_ut=_vec_or(a, "diurnal_amplitude_ut", "ambient", (0.0, 0.0, 0.0)),
        **_floats(a, AmbientConfig, ("diurnal_period_s", "flicker_ut", "traffic_rate_per_h",
                                     "traffic_field_ut", "traffic_distance_m",
                                     "traffic_duration_s", "lab_temperature_swing_c")),
    )  # fmt: skip


def _floats(d: dict[str, Any], cls: type, names: tuple[str, ...]) -> dict[str, float]:
    """The numbers ``names`` of a table, each defaulting to its field's default in ``cls``."""
    defaults = {f.name: f.default for f in fields(cls)}
    return {name: float(d.get(name, defaults[name])) for name in names}


def _supply(s: dict[str, Any], where: str) -> SupplyConfig:
    axis, trim = s.get("axis"), s.get("trim")
    if axis is not None and axis not in AXES:
        raise SimConfigError(f"{where}.axis must be x, y or z")
    if trim is not None and (trim not in AXES or axis is not None):
        raise SimConfigError(f"{where}.trim must be x, y or z, on a supply with no axis")
    return SupplyConfig(
        name=str(s["name"]),
        kind=str(s["kind"]),
        endpoint=_endpoint(s, where),
        axis=None if axis is None else AXES[axis],
        trim=None if trim is None else AXES[trim],
        model_id=int(s.get("model_id", 60125)),
        current_range=int(s.get("current_range", 0)),
        regmap=str(s.get("regmap", "")),
        resistance_ohm=float(s.get("resistance_ohm", 5.0)),
        tau_s=float(s.get("tau_s", 0.002)),
        input_voltage_v=float(s.get("input_voltage_v", 48.0)),
        **_floats(s, SupplyConfig, ("gain_ppm", "gain_drift_ppm_per_h", "gain_ppm_per_k")),
    )


def _supplies(raw: dict[str, Any]) -> list[SupplyConfig]:
    supplies = [_supply(s, f"supplies[{i}]") for i, s in enumerate(raw.get("supplies", []))]
    axes_driven = sorted(s.axis for s in supplies if s.axis is not None)
    if axes_driven != [0, 1, 2]:
        raise SimConfigError("supplies must drive each coil axis x, y, z exactly once")
    return supplies


def _vec_or(
    m: dict[str, Any], key: str, where: str, default: tuple[float, ...]
) -> tuple[float, ...]:
    return _vec(m, key, where) if key in m else default


def _magnetometer(m: dict[str, Any], where: str, loads: set[str]) -> MagnetometerConfig:
    zero = (0.0, 0.0, 0.0)
    mag = MagnetometerConfig(
        name=str(m["name"]),
        kind=str(m["kind"]),
        endpoint=_endpoint(m, where),
        scale=_vec_or(m, "scale", where, (1.0, 1.0, 1.0)),
        nonorth_deg=_vec_or(m, "nonorth_deg", where, zero),
        mounting_deg=_vec_or(m, "mounting_deg", where, zero),
        offset_ut=_vec_or(m, "offset_ut", where, zero),
        k_ut_per_a={
            k: _vec({"v": v}, "v", f"{where}.k_ut_per_a.{k}")
            for k, v in m.get("k_ut_per_a", {}).items()
        },
        delay_s={k: float(v) for k, v in m.get("delay_s", {}).items()},
        noise_ut=float(m.get("noise_ut", 0.0)),
        rate_hz=float(m.get("rate_hz", 20.0)),
        serial_number=str(m.get("serial_number", "0001")),
        i2c_address=int(m.get("i2c_address", 0x20)),
        line_format=str(m.get("line_format", "{x:.4f} {y:.4f} {z:.4f}")),
        temperature_ref_c=float(m.get("temperature_ref_c", 25.0)),
        scale_per_k=float(m.get("scale_per_k", 0.0)),
        offset_ut_per_k=_vec_or(m, "offset_ut_per_k", where, zero),
        position_m=_vec_or(m, "position_m", where, zero),
        role=None if m.get("role") is None else str(m["role"]),
        certificate_scale_sigma=float(m.get("certificate_scale_sigma", 0.0)),
        certificate_angle_sigma_arcsec=float(m.get("certificate_angle_sigma_arcsec", 0.0)),
        certificate_mounting_sigma_arcsec=float(m.get("certificate_mounting_sigma_arcsec", 0.0)),
        optical_axis=_vec_or(m, "optical_axis", where, (0.0, 0.0, 1.0)),
        scalar_offset_nt=float(m.get("scalar_offset_nt", 0.0)),
        heading_error_nt=float(m.get("heading_error_nt", 0.0)),
        dead_zone_deg=float(m.get("dead_zone_deg", 10.0)),
        offset_drift_nt_per_h=_vec_or(m, "offset_drift_nt_per_h", where, zero),
        offset_walk_nt_per_sqrt_h=float(m.get("offset_walk_nt_per_sqrt_h", 0.0)),
        offset_flicker_nt=float(m.get("offset_flicker_nt", 0.0)),
        cross_field_ppm_per_ut=_mat(m, "cross_field_ppm_per_ut", where)
        if "cross_field_ppm_per_ut" in m
        else ((0.0,) * 3,) * 3,
        perming_threshold_ut=float(m.get("perming_threshold_ut", 0.0)),
        perming_nt_per_ut=float(m.get("perming_nt_per_ut", 0.0)),
        offset_hysteresis_nt=_vec_or(m, "offset_hysteresis_nt", where, zero),
        hysteresis_band_k=float(m.get("hysteresis_band_k", 1.0)),
        response_integration_s=float(m.get("response_integration_s", 0.0)),
        response_tau_s=float(m.get("response_tau_s", 0.0)),
    )
    _check_dut_truth(mag, where)
    if mag.offset_walk_nt_per_sqrt_h < 0 or mag.offset_flicker_nt < 0:
        raise SimConfigError(
            f"{where}: offset_walk_nt_per_sqrt_h and offset_flicker_nt must be >= 0"
        )
    if mag.role not in (None, "reference", "ambient", "scalar"):
        raise SimConfigError(f"{where}.role must be 'reference', 'ambient' or 'scalar' (or absent)")
    if not any(mag.optical_axis):
        raise SimConfigError(f"{where}.optical_axis must not be zero")
    for ch in mag.k_ut_per_a:
        if ch not in loads:
            raise SimConfigError(f"{where}.k_ut_per_a names '{ch}', which is no load channel")
    return mag


def _check_dut_truth(mag: MagnetometerConfig, where: str) -> None:
    """The characterization truths' ranges (response, hysteresis, perming)."""
    if mag.response_integration_s < 0 or mag.response_tau_s < 0:
        raise SimConfigError(f"{where}: response_integration_s and response_tau_s must be >= 0")
    if not mag.hysteresis_band_k > 0:
        raise SimConfigError(f"{where}: hysteresis_band_k must be > 0")
    if mag.perming_threshold_ut < 0 or mag.perming_nt_per_ut < 0:
        raise SimConfigError(f"{where}: perming_threshold_ut and perming_nt_per_ut must be >= 0")


def _thermal(t: dict[str, Any], loads: set[str]) -> ThermalConfig:
    thermal = ThermalConfig(str(t["heater"]), float(t.get("ambient_c", 25.0)),
                            float(t.get("k_per_w", 1.0)), float(t.get("tau_s", 60.0)))  # fmt: skip
    if thermal.heater not in loads:
        raise SimConfigError(f"thermal.heater names '{thermal.heater}', which is no load channel")
    if not (thermal.tau_s > 0 and thermal.k_per_w >= 0):
        raise SimConfigError("thermal: tau_s must be > 0 and k_per_w >= 0")
    return thermal


FAULT_KEYS = frozenset({"reply_delay_s", "silent", "drop_rate", "corrupt_rate", "exception_code",
                        "disconnect", "stuck"})  # fmt: skip
"""The fields of ``sim.physics.Faults`` a ``[faults.NAME]`` table may set."""


def _faults(raw: dict[str, Any], names: set[str]) -> dict[str, dict[str, float | bool | int]]:
    faults: dict[str, dict[str, float | bool | int]] = {}
    for name, table in raw.get("faults", {}).items():
        if name not in names:
            raise SimConfigError(f"faults.{name}: no device of that name")
        unknown = set(table) - FAULT_KEYS
        if unknown:
            raise SimConfigError(
                f"faults.{name}: unknown keys {sorted(unknown)}; use {sorted(FAULT_KEYS)}"
            )
        faults[name] = dict(table)
    return faults


def _parse(raw: dict[str, Any], source: str) -> SimConfig:
    cage = _cage(raw["cage"])
    ambient = _ambient(raw["ambient"])
    supplies = _supplies(raw)
    loads = {s.name for s in supplies if s.axis is None and s.trim is None}
    relay = None
    if "relay" in raw:
        r = raw["relay"]
        relay = RelayConfig(str(r["name"]), str(r["regmap"]), _endpoint(r, "relay"))
    if cage.polarity == "relay" and relay is None:
        raise SimConfigError("cage.polarity = 'relay' needs a [relay] device")
    mags = [_magnetometer(m, f"magnetometers[{i}]", loads)
            for i, m in enumerate(raw.get("magnetometers", []))]  # fmt: skip
    thermal = _thermal(raw["thermal"], loads) if "thermal" in raw else None
    thermometer = None
    if "thermometer" in raw:
        t = raw["thermometer"]
        thermometer = ThermometerConfig(
            str(t["name"]), str(t["regmap"]), _endpoint(t, "thermometer")
        )
    names = {s.name for s in supplies} | {m.name for m in mags} | ({relay.name} if relay else set())
    names |= {thermometer.name} if thermometer else set()
    return SimConfig(int(raw.get("seed", 0)), cage, ambient, tuple(supplies),
                     relay, tuple(mags), source, _faults(raw, names), thermal, thermometer)  # fmt: skip
