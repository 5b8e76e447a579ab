"""What the rig may ask of each role of device: coil supply, load-current channel, polarity relay,
magnetometer and thermometer. Every driver satisfies one or more of these Protocols (checked by mypy where the
registry opens it, see :mod:`drivers.registry`); the rig never asks a driver for its class.

Units are in the names: V, A, uT, Hz, s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from drivers.identity import Identity

Vector = tuple[float, float, float]


@dataclass(frozen=True)
class SupplyReading:
    """Set-points and measured output of a supply or load (V, A, W), as one read returns them."""

    v_set_v: float
    i_set_a: float
    v_out_v: float
    i_out_a: float
    output_on: bool
    constant_current: bool
    protection: str  # "" (none), "OVP", "OCP", "OPP", "OTP", "SCP" or "code N"
    power_w: float | None = None  # the device's own power reading; None where it has none


@dataclass(frozen=True)
class ProtectionLevel:
    """One protection trip level as the instrument holds it: ``kind`` "OVP" (V), "OCP" (A) or
    "OPP" (W), its ``value`` in that unit, and ``register``, where it is (for messages), e.g.
    "register 's_ovp' (0x0052)"."""

    kind: str
    value: float
    register: str

    @property
    def unit(self) -> str:
        """V, A or W."""
        return PROTECTION_UNITS[self.kind]


PROTECTION_UNITS = {"OVP": "V", "OCP": "A", "OPP": "W"}
"""The unit of each protection level."""


@runtime_checkable
class Protected(Protocol):
    """An output whose protection levels can be read and set (every supply and load the rig
    knows: the Riden's M0 OVP/OCP, a register map's ``ovp``/``ocp``/``opp`` registers)."""

    def protection_levels(self) -> tuple[ProtectionLevel, ...]:
        """Every protection level the instrument has, as it reads now."""
        ...

    def set_protection_levels(self, *, ovp_v: float | None = None, ocp_a: float | None = None,
                              opp_w: float | None = None) -> tuple[ProtectionLevel, ...]:  # fmt: skip
        """Write the levels given (None: left as is), then read every level back. Raises
        LimitError for a level the instrument does not have or cannot hold, DeviceProtocolError
        when one reads back other than written."""
        ...


class Output(Protocol):
    """Anything that can drive current: it identifies itself, goes safe and closes."""

    name: str

    def identify(self) -> Identity: ...
    def safe(self) -> None: ...
    def close(self) -> None: ...


class Load(Output, Protocol):
    """A load-current channel: a supply into a harness, or an electronic load (current source)."""

    @property
    def max_current_a(self) -> float: ...
    def set_current(self, amps: float) -> float: ...
    def set_output(self, on: bool) -> None: ...
    def read(self) -> SupplyReading: ...
    def enable_as_load(self, compliance_v: float) -> None:
        """Current set-point 0, the voltage set-point to ``compliance_v`` (capped at the device's
        range) where the device has one, then the output (or load input) on."""
        ...


class Supply(Load, Protocol):
    """A coil supply: voltage and current set-points, signed current if ``bipolar``."""

    @property
    def max_voltage_v(self) -> float: ...
    @property
    def bipolar(self) -> bool: ...
    def set_voltage(self, volts: float) -> float: ...


class Relay(Output, Protocol):
    """Polarity relays (one H-bridge per coil axis)."""

    def polarity(self, axis: int) -> int: ...
    def set_polarity(self, axis: int, sign: int) -> None: ...


class Magnetometer(Protocol):
    """A three-axis magnetometer returning uT.

    Sampling: :meth:`start_sampling` sets the sensor up for a rate (the driver picks the nearest
    rate the sensor can do, and its mode: streaming or polled) and returns the rate it runs at.
    When ``self_timed`` is true the sensor sends at its own pace and :meth:`read_samples` returns
    whatever arrived (oldest first, one sensor period apart); otherwise the caller paces the calls
    and each returns one fresh sample.
    """

    name: str

    @property
    def self_timed(self) -> bool: ...
    def identify(self) -> Identity: ...
    def read(self) -> Vector: ...
    def start_sampling(self, rate_hz: float) -> float: ...
    def read_samples(self, max_wait_s: float) -> list[Vector]: ...
    def stop_sampling(self) -> None: ...
    def close(self) -> None: ...


@runtime_checkable
class CountsLostSamples(Protocol):
    """A self-timed magnetometer that knows which of its samples it lost (damaged or cut-short
    frames it skipped): ``lost_before[i]`` is how many of the sensor's samples were lost just
    before sample ``i`` of the last :meth:`Magnetometer.read_samples` (empty when none). The
    sampler numbers the stream's samples by it, so a lost frame does not misdate the next ones."""

    @property
    def lost_before(self) -> tuple[int, ...]: ...


@runtime_checkable
class SetReset(Protocol):
    """A magnetometer with set/reset pulses (an AMR sensor's strap: they restore its magnetization,
    so a strong field's perming goes): automatic pulses (the sensor's default, removing perming as
    it reads) on or off, and one pulse now. Called only while the sensor is not sampling."""

    def set_reset_auto(self, on: bool) -> None: ...
    def set_reset_pulse(self) -> None: ...


class ScalarMagnetometer(Protocol):
    """A total-field magnetometer (cesium, Overhauser) returning nT: its scale is a physical
    constant, so it needs no calibration certificate. Streams at the rate :meth:`set_cycle` sets;
    :meth:`read_total_nt` returns the next reading, None when the sensor had no signal (a cesium
    cell's dead zones, a field outside its range)."""

    name: str

    def identify(self) -> Identity: ...
    def set_cycle(self, rate_hz: float) -> float: ...
    def flush(self) -> None: ...
    def read_total_nt(self) -> float | None: ...
    def close(self) -> None: ...


class Thermometer(Protocol):
    """A temperature reading (degrees C), e.g. an RTD on the DUT's mount: recorded through a run
    so that the DUT's temperature coefficients can be fitted (``rig calibrate RUN --temperature``)."""

    name: str

    def identify(self) -> Identity: ...
    def read_temperature_c(self) -> float: ...
    def close(self) -> None: ...
