"""The one list of device kinds: for each, its driver, the transports it accepts, its configuration
parameters (types, which are required), its roles and how ``rig devices scan`` recognizes it.

The rig derives everything from here: configuration checking (``rig.config``), opening devices
(``rig.devices``), the guardian's list of outputs and bring-up (``rig.bringup``). Adding a device:

* a Modbus supply, load, relay board or thermometer whose registers are plain numbers: one
  register-map TOML in ``regmaps/`` (used as ``kind = "regmap-supply"`` / ``"regmap-eload"`` /
  ``"regmap-relay"`` / ``"regmap-thermometer"`` with ``regmap = "<file name>"``): no entry here;
* anything else: one driver module satisfying a Protocol of :mod:`drivers.protocols`, plus one
  :class:`DeviceKind` in ``_modbus_kinds()``, ``_magnetometer_kinds()`` or ``_scalar_kinds()``
  below (and the class in ``_satisfies``).

See ``docs/devices.md``.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal

from drivers.config_keys import (
    DATE,
    LIST,
    NUMBER,
    STANDARD_BAUDRATES,
    TEXT,
    WHOLE,
    WHOLE_OR_TEXT,
    Param,
)
from drivers.errors import DeviceError
from drivers.identity import Identity
from drivers.mag.ascii_line import AsciiLineMagnetometer, LineFormat
from drivers.mag.geometrics_counter import GeometricsCounter
from drivers.mag.geometrics_counter import parse_line as parse_counter_line
from drivers.mag.hmr2300 import Hmr2300
from drivers.mag.lis3mdl import WHO_AM_I, WHO_AM_I_VALUE, Lis3mdl
from drivers.mag.rm3100 import REVID, REVID_VALUE, Rm3100
from drivers.protocols import Load, Magnetometer, Relay, ScalarMagnetometer, Supply, Thermometer
from drivers.psu.regmap_device import (
    MappedDevice,
    MappedSupply,
    MappedThermometer,
    PolarityRelay,
)
from drivers.psu.riden import MODELS as RIDEN_MODELS
from drivers.psu.riden import RidenSupply, riden_model
from drivers.transport.i2c import I2CDevice
from drivers.transport.modbus import ModbusLink
from drivers.transport.serial_port import SerialPort
from regmaps import RegisterMap, load_map, shipped_maps

Role = Literal["supply", "load", "relay", "magnetometer", "scalar", "thermometer"]
OUTPUT_ROLES: frozenset[Role] = frozenset({"supply", "load", "relay"})

PATH = Param("path", TEXT, True, help="serial port, e.g. /dev/ttyUSB0 (or a pyserial URL)",
             nonempty=True, fix='write the port, e.g. path = "/dev/ttyUSB0"')  # fmt: skip
BAUDRATE = Param("baudrate", WHOLE, False, 115200, "baud rate", choices=STANDARD_BAUDRATES,
                 why="a standard baud rate",
                 fix="write the rate set on the device (its menu or manual shows it),"
                     " e.g. baudrate = 9600", unit="Bd")  # fmt: skip
MODBUS_ID_FIX = (
    "write the Modbus address set on the device (its menu or DIP switches show it),"
    " e.g. device_id = 1"
)
TIMEOUT = Param("timeout_s", NUMBER, False, 0.5, "reply timeout", above=0.0,
                fix="write the seconds to wait for a reply, e.g. timeout_s = 0.5", unit="s")  # fmt: skip

TRANSPORTS: dict[str, tuple[Param, ...]] = {
    "modbus-tcp": (
        Param("host", TEXT, True, help="IP address or host name", nonempty=True,
              fix='write the device\'s or gateway\'s address, e.g. host = "192.168.1.50"'),
        Param("port", WHOLE, True, None, "the port the device listens on (Modbus TCP's own: 502)", low=1, high=65535,
              why="a TCP port",
              fix="write the port the device listens on, e.g. port = 502 (Modbus TCP's own)"),
        Param("device_id", WHOLE, False, 1, "Modbus unit id", low=0, high=255,
              why="a Modbus TCP unit id: 1-247 picks a serial device behind a gateway; a device"
                  " on the network itself usually answers 255 or 0, or ignores the id",
              fix=MODBUS_ID_FIX),
        TIMEOUT,
    ),
    "modbus-rtu": (
        PATH,
        BAUDRATE,
        Param("parity", TEXT, False, "N", "N (none), E (even) or O (odd)", choices=("N", "E", "O"),
              why="a parity (none, even, odd)", fix='write the parity set on the device, e.g. parity = "N"'),
        Param("device_id", WHOLE, False, 1, "Modbus device (slave) id", low=1, high=247,
              why="a Modbus RTU address: 0 is the broadcast address, which no device answers;"
                  " 248-255 are reserved",
              fix=MODBUS_ID_FIX),
        TIMEOUT,
    ),
    "serial": (
        PATH,
        replace(BAUDRATE, default=None),  # each serial kind states its own (transport_keys)
    ),
    "i2c": (
        Param("address", WHOLE, True, help="7-bit I2C address, e.g. 0x20", low=0x08, high=0x77,
              why="7-bit I2C addresses 0x08-0x77; 0x00-0x07 and 0x78-0x7F are reserved",
              fix="write the chip's address from its datasheet, e.g. address = 0x20"),
        Param("bus", WHOLE_OR_TEXT, False, 1, "bus number N of /dev/i2c-N"),
    ),
}  # fmt: skip
"""Each transport's connection parameters."""

RECORD_KEYS: tuple[Param, ...] = (
    Param("serial", TEXT, help="the instrument's serial number (on the report and in the lab index)"),
    Param("calibrated_on", DATE, help="date of its calibration certificate (on the report and in the lab index)"),
    Param("certificate_expires", DATE,
          help="the certificate's expiry date (a run after it warns, its report flags it, the lab index lists it)"),
)  # fmt: skip
"""Keys every kind accepts; no driver reads them: they are copied into each run folder and read by
the lab index (``rig.lab.summary``, ``docs/lab.md``)."""


def transport_param(protocol: str, name: str) -> Param:
    """One connection parameter of a transport, e.g. ``transport_param("modbus-tcp", "port")``."""
    return next(p for p in TRANSPORTS[protocol] if p.name == name)


@dataclass(frozen=True)
class OpenSpec:
    """What a kind's ``open`` gets: the device's name, transport and parameters (the registered
    opener fills in the declared defaults), and for I2C the bus (a number or an smbus2-compatible
    object)."""

    name: str
    protocol: str
    params: Mapping[str, Any]
    i2c_bus: Any = None

    def get(self, key: str, default: Any = None) -> Any:
        """A parameter, or ``default``."""
        value = self.params.get(key)
        return default if value is None else value


@dataclass(frozen=True)
class ProbeTarget:
    """One place ``rig devices scan`` looks: a transport and its connection parameters (``path``
    and ``baudrate``, ``host`` and ``port``, or ``bus``), for I2C the open bus object."""

    protocol: str
    params: Mapping[str, Any]
    timeout_s: float = 0.2
    i2c_bus: Any = None

    @property
    def where(self) -> str:
        """Human-readable place (port, host:port or bus)."""
        p = self.params
        if "host" in p:
            return f"{p['host']}:{p['port']}"
        if "path" in p:
            return str(p["path"])
        return f"i2c bus {p.get('bus')}"


@dataclass(frozen=True)
class Found:
    """A device that answered a kind's identify exchange: what to write in ``[devices.NAME]``."""

    kind: str
    protocol: str
    model: str
    serial: str
    params: dict[str, Any]
    where: str
    warning: str = ""
    """A caveat about the identification ("" for none), e.g. a model code its map does not list."""


Opener = Callable[[OpenSpec], Any]
Prober = Callable[[ProbeTarget], list[Found]]


@dataclass(frozen=True)
class OutputRange:
    """What a supply or load's kind and configuration say of its range before it is opened: the
    most current (A) and voltage (V) it can give, whether its current is signed, whether it has a
    voltage set-point (an electronic load has none), and where that comes from (words)."""

    max_current_a: float
    max_voltage_v: float
    bipolar: bool
    sets_voltage: bool
    source: str


@dataclass(frozen=True)
class DeviceKind:
    """A registered kind of device.

    ``open`` builds the driver from a spec whose declared defaults are filled in; ``probe``
    (optional) recognizes the device on a bring-up target of one of ``transports`` at each of
    ``probe_baudrates`` (serial lines only); ``probe_first`` kinds are tried before the others on a
    serial port (a passive listen before any request). ``transport_keys`` holds this kind's own
    version of a transport key (the HMR2300's baud rate defaults to 9600 Bd). ``range_of``
    (supplies and loads) tells an output's range from its configuration before it is opened
    (``rig check``'s heat limits).
    """

    name: str
    roles: frozenset[Role]
    transports: tuple[str, ...]
    params: tuple[Param, ...]
    open: Opener
    description: str
    probe: Prober | None = None
    probe_baudrates: tuple[int, ...] = ()
    probe_first: bool = False
    transport_keys: Mapping[str, Param] = field(default_factory=dict)
    range_of: Callable[[Mapping[str, Any]], OutputRange | None] | None = None

    @property
    def is_output(self) -> bool:
        """Supplies, loads and relays: the guardian switches them off if the rig dies."""
        return bool(self.roles & OUTPUT_ROLES)

    def param_specs(self, protocol: str) -> tuple[Param, ...]:
        """Every key a device of this kind over ``protocol`` accepts: the transport's (with this
        kind's defaults), the kind's own, then :data:`RECORD_KEYS`."""
        transport = tuple(self.transport_keys.get(p.name, p) for p in TRANSPORTS[protocol])
        return transport + self.params + RECORD_KEYS

    def defaults(self, protocol: str) -> dict[str, Any]:
        """The declared defaults over ``protocol`` (keys without one are left out), fresh copies."""
        return {p.name: copy.copy(p.default) for p in self.param_specs(protocol)
                if p.default is not None}  # fmt: skip


KINDS: dict[str, DeviceKind] = {}


def register(kind: DeviceKind) -> DeviceKind:
    """Add a kind (its name must be new; its transports must be known). Its opener is wrapped so
    that it always sees the declared defaults, however the spec was made."""
    if kind.name in KINDS:
        raise ValueError(f"device kind '{kind.name}' is registered twice")
    unknown = set(kind.transports) - set(TRANSPORTS)
    if unknown:
        raise ValueError(f"device kind '{kind.name}': unknown transports {sorted(unknown)}")
    opener = kind.open

    def open_with_defaults(spec: OpenSpec) -> Any:
        return opener(replace(spec, params=kind.defaults(spec.protocol) | dict(spec.params)))

    KINDS[kind.name] = replace(kind, open=open_with_defaults)
    return KINDS[kind.name]


def kinds_with_role(role: Role) -> list[str]:
    """Names of the kinds that can play ``role``."""
    return [k.name for k in KINDS.values() if role in k.roles]


def output_kinds() -> tuple[str, ...]:
    """Names of the kinds the guardian switches off (supplies, loads, relays)."""
    return tuple(k.name for k in KINDS.values() if k.is_output)


def all_params() -> dict[str, Param]:
    """Every parameter any transport or kind declares, by name (one type per name)."""
    out: dict[str, Param] = {}
    for params in [*TRANSPORTS.values(), *(k.params for k in KINDS.values()), RECORD_KEYS]:
        for p in params:
            out.setdefault(p.name, p)
    return out


# --- helpers the openers share -------------------------------------------------------------------


def transport_defaults(protocol: str) -> dict[str, Any]:
    """The declared defaults of a transport's keys (for a link opened outside a kind's opener)."""
    return {p.name: p.default for p in TRANSPORTS[protocol] if p.default is not None}


def modbus_link(spec: OpenSpec, *, baudrate: int | None = None, retries: int = 2) -> ModbusLink:
    """The Modbus link of a ``modbus-tcp`` or ``modbus-rtu`` device (declared defaults applied);
    ``baudrate`` is the rate when the spec gives none (a register map's factory rate)."""
    p = transport_defaults(spec.protocol) | {k: v for k, v in spec.params.items() if v is not None}
    timeout, device_id = float(p["timeout_s"]), int(p["device_id"])
    if spec.protocol == "modbus-tcp":
        return ModbusLink(name=spec.name, host=str(p["host"]), port=int(p["port"]),
                          device_id=device_id, timeout_s=timeout, retries=retries)  # fmt: skip
    rate = spec.get("baudrate") or baudrate or p["baudrate"]
    return ModbusLink(name=spec.name, path=str(p["path"]), baudrate=int(rate),
                      parity=str(p["parity"]), device_id=device_id, timeout_s=timeout,
                      retries=retries)  # fmt: skip


def _float_or_none(value: Any) -> float | None:
    return None if value is None else float(value)


# --- Riden RD60xx -------------------------------------------------------------------------------


def _open_riden(spec: OpenSpec) -> RidenSupply:
    link = modbus_link(spec)
    try:  # the driver asks the model at once: a wrong id or model must not leave the port open
        current_range = spec.get("current_range")
        return RidenSupply(link, name=spec.name,
                           max_voltage_v=_float_or_none(spec.get("max_voltage_v")),
                           max_current_a=_float_or_none(spec.get("max_current_a")),
                           current_range=None if current_range is None else int(current_range))  # fmt: skip
    except BaseException:
        link.close()
        raise


def _probe_link(target: ProbeTarget, name: str, baudrate: int | None = None) -> ModbusLink:
    params = dict(target.params) | {"timeout_s": target.timeout_s}
    if baudrate is not None:
        params["baudrate"] = baudrate
    spec = OpenSpec(f"scan:{name}", target.protocol, params)
    return modbus_link(spec, retries=0)


def _connection(target: ProbeTarget) -> dict[str, Any]:
    keys = ("host", "port", "device_id") if target.protocol == "modbus-tcp" else (
        "path", "baudrate", "device_id")  # fmt: skip
    return {k: target.params[k] for k in keys if k in target.params}


def _probe_riden(target: ProbeTarget) -> list[Found]:
    try:
        link = _probe_link(target, "riden-rd60xx")
    except DeviceError:
        return []
    try:
        regs = link.read_registers(0, 4)
    except DeviceError:
        return []
    finally:
        link.close()
    model = riden_model(regs[0])
    if model is None:  # bring-up lists it with the registers it read (an unknown model id)
        return []
    return [Found("riden-rd60xx", target.protocol, model.name, str((regs[1] << 16) | regs[2]),
                  _connection(target), target.where)]  # fmt: skip


# --- register-map devices -----------------------------------------------------------------------


def _mapped(spec: OpenSpec) -> tuple[ModbusLink, RegisterMap]:
    """A register-map device's map and its Modbus link (the map's baud rate unless given)."""
    regmap = load_map(str(spec.get("regmap")))
    return modbus_link(spec, baudrate=regmap.baudrate), regmap


def _open_mapped_supply(spec: OpenSpec) -> MappedSupply:
    return MappedSupply(*_mapped(spec), name=spec.name,
                        max_voltage_v=_float_or_none(spec.get("max_voltage_v")),
                        max_current_a=_float_or_none(spec.get("max_current_a")))  # fmt: skip


def _open_relay(spec: OpenSpec) -> PolarityRelay:
    return PolarityRelay(*_mapped(spec), name=spec.name)


def _open_thermometer(spec: OpenSpec) -> MappedThermometer:
    return MappedThermometer(*_mapped(spec), name=spec.name)


def _identifiable_maps(map_kind: str) -> list[RegisterMap]:
    return [m for m in shipped_maps() if m.kind == map_kind and m.identity_registers()]


def _probe_maps(kind_name: str, map_kind: str) -> Prober:
    """Recognize a device by the identity registers (constants, model code) of a shipped map
    (:meth:`MappedDevice.identify`, reads only)."""

    def probe(target: ProbeTarget) -> list[Found]:
        baud = target.params.get("baudrate")
        for regmap in _identifiable_maps(map_kind):
            if target.protocol == "modbus-rtu" and (regmap.baudrate or 115200) != baud:
                continue
            try:
                link = _probe_link(target, kind_name)
            except DeviceError:
                return []
            try:
                ident: Identity | None = MappedDevice(link, regmap, f"scan:{kind_name}").identify()
            except DeviceError:
                ident = None
            finally:
                link.close()
            if ident is not None:
                params = _connection(target) | {"regmap": regmap.name}
                return [Found(kind_name, target.protocol, ident.model, ident.serial, params,
                              target.where, ident.warning)]  # fmt: skip
        return []

    return probe


def _map_bauds(map_kind: str) -> tuple[int, ...]:
    return tuple(sorted({m.baudrate or 115200 for m in _identifiable_maps(map_kind)}))


# --- magnetometers ------------------------------------------------------------------------------


def _open_hmr2300(spec: OpenSpec) -> Hmr2300:
    device_id = spec.get("device_id")
    return Hmr2300(str(spec.get("path")), baudrate=int(spec.get("baudrate")),
                   device_id=None if device_id is None else int(device_id), name=spec.name)  # fmt: skip


def _probe_hmr2300(target: ProbeTarget) -> list[Found]:
    baud = int(target.params["baudrate"])
    try:
        mag = Hmr2300(str(target.params["path"]), baudrate=baud, timeout_s=target.timeout_s,
                      retries=0, name="scan:hmr2300", set_reset_auto=False)  # fmt: skip
    except DeviceError:
        return []
    try:
        ident = mag.identify()
    except DeviceError:
        ident = Identity("HMR2300", "", "")
    finally:
        mag.close()
    params = {"path": target.params["path"], "baudrate": baud, "device_id": mag.device_id}
    return [Found("hmr2300", "serial", ident.model, ident.serial, params, target.where)]


def _open_ascii(spec: OpenSpec) -> AsciiLineMagnetometer:
    columns = tuple(int(c) for c in spec.get("columns"))
    if len(columns) != 3:
        raise ValueError(f"device '{spec.name}': columns must name 3 columns, e.g. [0, 1, 2]")
    fmt = LineFormat(delimiter=spec.get("delimiter"), columns=(columns[0], columns[1], columns[2]),
                     scale_to_ut=float(spec.get("scale_to_ut")))  # fmt: skip
    return AsciiLineMagnetometer(str(spec.get("path")), baudrate=int(spec.get("baudrate")),
                                 fmt=fmt, name=spec.name)  # fmt: skip


def _listening_probe(kind: str, model: str, parse: Callable[[bytes], Any]) -> Prober:
    """Recognize a streaming sensor by listening (sending nothing): two consecutive lines that
    ``parse`` accepts (it raises a DeviceError otherwise)."""

    def probe(target: ProbeTarget) -> list[Found]:
        baud = int(target.params["baudrate"])
        try:
            port = SerialPort(str(target.params["path"]), baud,
                              timeout_s=max(target.timeout_s, 0.3), name=f"scan:{kind}")  # fmt: skip
        except DeviceError:
            return []
        try:
            port.drain_input(quiet_s=0.0)
            port.read_until(b"\n")  # the partial line in flight
            for _ in range(2):
                parse(port.read_until(b"\n"))
        except DeviceError:
            return []
        finally:
            port.close()
        params = {"path": target.params["path"], "baudrate": baud}
        return [Found(kind, "serial", model, "", params, target.where)]

    return probe


_probe_ascii = _listening_probe("ascii-mag", "ASCII line magnetometer", LineFormat().parse)
"""Two consecutive lines of three or more numbers."""


def _i2c_bus(spec: OpenSpec) -> Any:
    return spec.i2c_bus if spec.i2c_bus is not None else int(spec.get("bus"))


def _probe_i2c(kind_name: str, model: str, addresses: tuple[int, ...], register: int,
               value: int) -> Prober:  # fmt: skip
    """Recognize a chip by an identity register (REVID, WHO_AM_I) at its possible addresses."""

    def probe(target: ProbeTarget) -> list[Found]:
        bus = target.i2c_bus if target.i2c_bus is not None else target.params.get("bus")
        found = []
        for address in addresses:
            try:
                dev = I2CDevice(bus, address, name=f"scan:{kind_name}", retries=0)
                if dev.read(register, 1)[0] != value:
                    continue
            except (DeviceError, OSError):
                continue
            params = {"bus": target.params.get("bus"), "address": address}
            found.append(
                Found(kind_name, "i2c", model, "", params, f"{target.where} {address:#04x}")
            )
        return found

    return probe


# --- the kinds ----------------------------------------------------------------------------------

SUPPLY_PARAMS: tuple[Param, ...] = (
    Param("max_current_a", NUMBER, help="current limit, below the device's own", above=0.0,
          fix="write the largest current this rig may ask for, e.g. max_current_a = 2.0", unit="A"),
    Param("max_voltage_v", NUMBER, help="voltage limit, below the device's own", above=0.0,
          fix="write the largest voltage this rig may ask for, e.g. max_voltage_v = 24.0", unit="V"),
    Param("compliance_v", NUMBER, False, 12.0, "voltage set-point when used as a load", above=0.0,
          fix="write the voltage set-point for use as a load, e.g. compliance_v = 12.0", unit="V"),
    Param("max_power_w", NUMBER, help="power limit: a current set-point whose worst case I x V"
          " (V: the voltage set-point, or the voltage limit when the output has none) exceeds it"
          " is refused, and a read-back V_out x I_out beyond it during a run is a fault",
          above=0.0, unit="W",
          fix="write the most power this output may deliver, e.g. max_power_w = 20"),
    Param("ovp_v", NUMBER, help="over-voltage protection level, written to the instrument (and"
          " read back) when the rig opens it; rig check warns when it is above the output's"
          " voltage limit", above=0.0, unit="V",
          fix="write the voltage at which the instrument must switch off, e.g. ovp_v = 13.0"),
    Param("ocp_a", NUMBER, help="over-current protection level, written and read back at open;"
          " rig check warns when it is above the output's current limit", above=0.0, unit="A",
          fix="write the current at which the instrument must switch off, e.g. ocp_a = 2.0"),
    Param("opp_w", NUMBER, help="over-power protection level (instruments that have one), written"
          " and read back at open; rig check warns when it is above max_power_w", above=0.0,
          unit="W", fix="write the power at which the instrument must switch off, e.g. opp_w = 20"),
    Param("heats", TEXT, help="the thermometer (a device name) this output warms, e.g. a heater"
          " pad on the DUT's mount: rig check predicts that thermometer's temperature, and it"
          " interlocks this output (docs/adr/0035)", nonempty=True,
          fix='write the thermometer\'s device name, e.g. heats = "dut_temp"'),
    Param("kelvin_per_w", NUMBER, help="with heats: the steady-state temperature rise per watt"
          " this output delivers", above=0.0, unit="K/W",
          fix="write the rise per watt, e.g. kelvin_per_w = 2.0 (measure it: a known power held"
          " for five time constants)"),
    Param("thermal_tau_s", NUMBER, help="with heats: the first-order time constant of that"
          " warming (absent: the steady state is reached at once, the safe assumption)", above=0.0,
          unit="s", fix="write the time constant, e.g. thermal_tau_s = 120"),
    Param("resistance_ohm", NUMBER, help="with heats: the heater's resistance, so the predicted"
          " power is min(I, V/R)^2 R instead of the worst case I x V", above=0.0, unit="ohm",
          fix="write the heater's resistance, e.g. resistance_ohm = 4.0"),
)  # fmt: skip
"""The limits every supply and load accepts, and how one that heats the DUT warms it."""
THERMOMETER_PARAMS: tuple[Param, ...] = (
    Param("max_temperature_c", NUMBER, help="the DUT's temperature limit: during every run a"
          " reading beyond it takes the outputs safe, and rig check refuses a heater plan"
          " predicted to pass it", low=-273.15, unit="C",
          fix="write the DUT's highest allowed temperature, e.g. max_temperature_c = 70"),
    Param("ambient_c", NUMBER, False, 25.0, "the temperature the DUT rests at with its heaters"
          " off: what rig check adds the heaters' predicted rise to", low=-273.15, unit="C",
          fix="write the lab's temperature, e.g. ambient_c = 25"),
)  # fmt: skip
"""A thermometer's keys: the DUT temperature interlock (ADR 0035)."""
REGMAP = Param("regmap", TEXT, True,
               help="a register-map file or a shipped map name, e.g. \"maynuo-m97\"")  # fmt: skip
MAP_BAUD = {"baudrate": replace(BAUDRATE, default=None,
                                help="baud rate (default: the register map's factory rate)")}  # fmt: skip
"""A register-map device's baud rate defaults to its map's (``[device].baudrate``)."""
CURRENT_RANGE = Param(
    "current_range", WHOLE, help="RD6012P only: 0 = the 6 A range (0.1 mA), 1 = 12 A (1 mA); written to"
                            " register 20 at open",
    choices=(0, 1), fix="write current_range = 0 (6 A, finer) or 1 (12 A)",
)  # fmt: skip
MAG_PARAMS: tuple[Param, ...] = (
    Param("rate_hz", NUMBER, False, 20.0, "sample rate", above=0.0,
          fix="write the samples per second, e.g. rate_hz = 20", unit="Hz"),
    Param("correction_matrix", LIST, help="calibration certificate: 3x3 matrix", shape=(3, 3),
          fix="write the certificate's matrix, e.g. [[1, 0, 0], [0, 1, 0], [0, 0, 1]]"),
    Param("correction_offset_ut", LIST, help="calibration certificate: offset", unit="uT",
          shape=(3,), fix="write the certificate's offset, e.g. [0.0, 0.0, 0.0]"),
    Param("correction_scale_sigma", NUMBER, False, 5e-5, "calibration certificate: 1-sigma of"
          " each scale factor, relative", above=0.0,
          fix="write the certificate's scale uncertainty, e.g. correction_scale_sigma = 5e-5"),
    Param("correction_angle_sigma_arcsec", NUMBER, False, 20.0, "calibration certificate: 1-sigma"
          " of each axis angle", above=0.0, unit="arcsec",
          fix="write the certificate's angle uncertainty, e.g. correction_angle_sigma_arcsec = 20"),
    Param("correction_mounting_sigma_arcsec", NUMBER, False, 30.0, "calibration certificate and"
          " fixture: 1-sigma of the sensor's rotation about each cage axis", above=0.0,
          unit="arcsec", fix="write how well the reference is aligned to the cage, e.g."
          " correction_mounting_sigma_arcsec = 30"),
    Param("position_m", LIST, help="where the sensor sits: m from the cage centre (the DUT's place),"
          " cage frame; a reference's place sets the budget's homogeneity terms", unit="m",
          shape=(3,), fix="write x, y, z in metres, e.g. position_m = [0.0, 0.0, -0.08]"),
    Param("noise_nt", NUMBER, help="white noise per reading, per axis (the datasheet's, or what a"
          " null_field step measured): rig check --predict uses it until a run has measured the"
          " noise", above=0.0, unit="nT", fix="write the noise per reading, e.g. noise_nt = 20"),
    Param("response_tau_s", NUMBER, False, 0.0, "the sensor's first-order low-pass time constant"
          " (datasheet or certificate): frequency_response removes a reference's own", low=0.0,
          unit="s", fix="write the time constant, e.g. response_tau_s = 0.001 (160 Hz corner)"),
    Param("response_integration_s", NUMBER, False, 0.0, "the sensor's conversion window (a"
          " boxcar before each reading's date): frequency_response removes a reference's own",
          low=0.0, unit="s", fix="write the window, e.g. response_integration_s = 0.013"),
    Param("stuck_after", WHOLE, False, 60, "identical readings in a row that mean a frozen"
          " sensor (0 = never judged)", low=0, high=1_000_000,
          fix="write a whole number of readings, e.g. stuck_after = 60 (3 s at 20 Hz)"),
    Param("stall_after_s", NUMBER, False, 1.5, "silence that means a stalled stream or a"
          " disconnected sensor (five sample periods are always allowed; time this computer held"
          " the data back is not counted)", low=0.1, high=600.0, unit="s",
          fix="write seconds of silence, e.g. stall_after_s = 1.5"),
)  # fmt: skip
"""The keys every magnetometer accepts."""
HMR2300_ID = Param("device_id", WHOLE, help="HMR2300 ID 00-98 (asked with *99ID= when absent)",
                   low=0, high=98, why="HMR2300 ids; 99 is its broadcast id",
                   fix="write the id the sensor answers *99ID= with, or leave device_id out")  # fmt: skip
ASCII_PARAMS: tuple[Param, ...] = (
    Param("delimiter", TEXT, help="column separator (whitespace when absent)"),
    Param("columns", LIST, False, [0, 1, 2], "x, y, z column numbers"),
    Param("scale_to_ut", NUMBER, False, 1.0, "multiplier from the line's unit to uT"),
)


def _modbus_kinds() -> Iterator[DeviceKind]:
    """Supplies, loads, relay boards and thermometers on Modbus."""
    modbus = ("modbus-tcp", "modbus-rtu")
    yield DeviceKind(
        "riden-rd60xx", frozenset({"supply", "load"}), modbus, (*SUPPLY_PARAMS, CURRENT_RANGE),
        _open_riden, "Riden RD60xx bench supply (RD6006, RD6006P, RK6006, RD6012, RD6012P, RD6018,"
        " RD6024, RD6030)", _probe_riden, (115200, 9600), range_of=_riden_range,
    )  # fmt: skip
    map_kinds: tuple[tuple[str, frozenset[Role], str, tuple[Param, ...], Opener, str], ...] = (
        ("regmap-supply", frozenset({"supply", "load"}), "supply", (REGMAP, *SUPPLY_PARAMS),
         _open_mapped_supply, "Modbus supply described by a register map (regmaps/)"),
        ("regmap-eload", frozenset({"load"}), "eload", (REGMAP, *SUPPLY_PARAMS),
         _open_mapped_supply, "Modbus electronic load described by a register map (regmaps/)"),
        ("regmap-relay", frozenset({"relay"}), "relay", (REGMAP,), _open_relay,
         "Modbus polarity relay board described by a register map"),
        ("regmap-thermometer", frozenset({"thermometer"}), "thermometer",
         (REGMAP, *THERMOMETER_PARAMS),
         _open_thermometer, "Modbus temperature module (RTD, thermocouple) described by a"
         " register map: recorded through every run (the DUT's temperature)"),
    )  # fmt: skip
    for name, roles, map_kind, params, opener, description in map_kinds:
        yield DeviceKind(name, roles, modbus, params, opener, description,
                         _probe_maps(name, map_kind), _map_bauds(map_kind), transport_keys=MAP_BAUD,
                         range_of=_map_range if map_kind in ("supply", "eload") else None)  # fmt: skip


def _magnetometer_kinds() -> Iterator[DeviceKind]:
    """Magnetometers on a serial line or I2C."""
    yield DeviceKind(
        "hmr2300", frozenset({"magnetometer"}), ("serial",), (HMR2300_ID, *MAG_PARAMS),
        _open_hmr2300, "Honeywell HMR2300 smart magnetometer (RS-232/RS-485)",
        _probe_hmr2300, (9600, 19200), transport_keys={"baudrate": replace(BAUDRATE, default=9600)},
    )  # fmt: skip
    yield DeviceKind(
        "ascii-mag", frozenset({"magnetometer"}), ("serial",), (*ASCII_PARAMS, *MAG_PARAMS),
        _open_ascii, "magnetometer sending one text line per sample (x y z)",
        _probe_ascii, (115200,), probe_first=True, transport_keys={"baudrate": BAUDRATE},
    )  # fmt: skip
    yield DeviceKind(
        "rm3100", frozenset({"magnetometer"}), ("i2c",), MAG_PARAMS,
        lambda s: Rm3100(_i2c_bus(s), int(s.get("address")), name=s.name),
        "PNI RM3100 on I2C", _probe_i2c("rm3100", "RM3100", (0x20, 0x21, 0x22, 0x23), REVID,
                                        REVID_VALUE),
    )  # fmt: skip
    yield DeviceKind(
        "lis3mdl", frozenset({"magnetometer"}), ("i2c",), MAG_PARAMS,
        lambda s: Lis3mdl(_i2c_bus(s), int(s.get("address")), name=s.name),
        "ST LIS3MDL on I2C", _probe_i2c("lis3mdl", "LIS3MDL", (0x1C, 0x1E), WHO_AM_I,
                                        WHO_AM_I_VALUE),
    )  # fmt: skip


SCALAR_PARAMS: tuple[Param, ...] = (
    Param("rate_hz", NUMBER, False, 10.0, "cycle rate the counter is set to", low=0.01,
          high=100.0, fix="write the readings per second, e.g. rate_hz = 10", unit="Hz"),
    Param("min_signal", WHOLE, False, 500, "the Larmor signal level (0-9999) below which a reading"
          " is not a measurement (a dead zone, a field out of range)", low=0, high=9999,
          fix="write the level, e.g. min_signal = 500 (locked readings show about 1200)"),
    Param("optical_axis", LIST, help="the cesium sensor's optical axis in the cage frame: the"
          " field directions within its dead zones are left out", shape=(3,),
          fix="write the axis as three numbers, e.g. optical_axis = [0.0, 0.5, 1.0]"),
    Param("dead_zone_deg", NUMBER, False, 15.0, "how far from the optical axis and from the plane"
          " normal to it a field must point to be measured", low=0.0, high=44.0, unit="deg",
          fix="write the sensor's dead zone with a margin, e.g. dead_zone_deg = 15"),
    Param("offset_sigma_nt", NUMBER, False, 3.0, "the sensor's stated absolute accuracy (1-sigma)",
          above=0.0, unit="nT", fix="write the accuracy, e.g. offset_sigma_nt = 3"),
    Param("position_m", LIST, help="where the sensor sits: m from the cage centre, cage frame",
          unit="m", shape=(3,), fix="write x, y, z in metres, e.g. position_m = [0.0, 0.0, 0.0]"),
)  # fmt: skip
"""A scalar magnetometer's keys."""


_probe_counter = _listening_probe(
    "geometrics-cm201", "Geometrics CM-201 counter (cesium)", parse_counter_line
)
"""Two consecutive lines in the counter's format."""


def _scalar_kinds() -> Iterator[DeviceKind]:
    """Total-field magnetometers."""
    yield DeviceKind(
        "geometrics-cm201", frozenset({"scalar"}), ("serial",), SCALAR_PARAMS,
        lambda s: GeometricsCounter(str(s.get("path")), baudrate=int(s.get("baudrate")),
                                    min_signal=int(s.get("min_signal")), name=s.name),
        "cesium total-field magnetometer behind a Geometrics CM-201/CM-221 counter (G-858, G-882)",
        _probe_counter, (9600, 19200), probe_first=True,
        transport_keys={"baudrate": replace(BAUDRATE, default=9600)},
    )  # fmt: skip


def output_range(kind: str, params: Mapping[str, Any]) -> OutputRange | None:
    """The range of an output of ``kind`` configured with ``params``, as known without opening
    it (its kind's ``range_of``); None for a kind that does not say or a map that cannot be read."""
    found = KINDS.get(kind)
    return found.range_of(params) if found is not None and found.range_of is not None else None


def _riden_range(params: Mapping[str, Any]) -> OutputRange:
    """A Riden's range as the largest of its family: the model is read when it is opened."""
    biggest = max(RIDEN_MODELS, key=lambda m: max(r.i_max_a for r in m.ranges))
    return OutputRange(max(r.i_max_a for r in biggest.ranges), max(m.v_max_v for m in RIDEN_MODELS),
                       False, True, f"the largest range of any riden-rd60xx ({biggest.name}); the"
                       " model is read when it is opened")  # fmt: skip


def _map_range(params: Mapping[str, Any]) -> OutputRange | None:
    """A register-map output's range from its map (None when the map cannot be read: opening
    the device says more)."""
    try:
        regmap = load_map(str(params.get("regmap")))
    except (OSError, ValueError):  # RegisterMapError is a ValueError
        return None
    return OutputRange(regmap.i_max, regmap.v_max, regmap.bipolar, regmap.role("v_set") is not None,
                       f"the range of its register map {regmap.name}")  # fmt: skip


def _iter_registered() -> Iterator[DeviceKind]:
    yield from _modbus_kinds()
    yield from _magnetometer_kinds()
    yield from _scalar_kinds()


for _kind in _iter_registered():
    register(_kind)


if TYPE_CHECKING:  # mypy checks that every driver satisfies the Protocols of its roles

    def _satisfies(
        riden: RidenSupply, mapped: MappedSupply, relay: PolarityRelay, hmr: Hmr2300,
        ascii_mag: AsciiLineMagnetometer, rm3100: Rm3100, lis3mdl: Lis3mdl,
        thermo: MappedThermometer, counter: GeometricsCounter,
    ) -> None:  # fmt: skip
        supplies: list[Supply] = [riden, mapped]
        loads: list[Load] = [riden, mapped]
        relays: list[Relay] = [relay]
        mags: list[Magnetometer] = [hmr, ascii_mag, rm3100, lis3mdl]
        thermometers: list[Thermometer] = [thermo]
        scalars: list[ScalarMagnetometer] = [counter]
        del supplies, loads, relays, mags, thermometers, scalars
