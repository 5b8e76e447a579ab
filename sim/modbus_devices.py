"""Modbus device models (pymodbus 3.16 ``SimDevice`` with an async action) bound to the physics.

The action runs on every access before pymodbus answers: reads refresh the live registers from
the physics; writes are checked and applied to the physics (or refused with a Modbus exception).
A Modbus TCP endpoint also answers for the unit ids it does not serve (:func:`unserved_ids`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any, ClassVar

from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

import timebase
from sim.device_kind import CageHost, SimKind
from sim.physics import CagePhysics, Faults, Supply, riden_model
from sim.regmap import Register, RegisterMap, load_regmap
from sim.regmap_coils import BIT_ONLY_CODES, COIL_CODES, pack, separate_spaces

if TYPE_CHECKING:
    from sim.config import SupplyConfig

Action = Callable[[int, int, int, int, list[int], Any], Coroutine[Any, Any, ExcCodes | None]]
READ_CODES = {1, 2, 3, 4}
WRITE_SINGLE = 6
"""pymodbus 3.16 answers a Write Single Register with the register read back after the write;
the Modbus application protocol (6.6) says the reply is an echo of the request, so the action
leaves the written word in place for that read (a trip shows in the next read instead)."""

# Riden RD60xx holding registers (ShayBox/Riden register.py, Baldanos/rd6006 registers.md, the
# riden-dongle firmware's riden_modbus_registers.h).
R_ID, R_SN_H, R_SN_L, R_FW = 0, 1, 2, 3
R_TEMP_C_SIGN, R_TEMP_C, R_TEMP_F_SIGN, R_TEMP_F = 4, 5, 6, 7
R_V_SET, R_I_SET, R_V_OUT, R_I_OUT, R_P_H, R_P_L, R_V_IN = 8, 9, 10, 11, 12, 13, 14
R_LOCK, R_PROTECT, R_CVCC, R_OUTPUT, R_PRESET, R_I_RANGE = 15, 16, 17, 18, 19, 20
R_CLOCK = range(48, 54)  # year, month, day, hour, minute, second
R_SETTINGS = range(66, 73)  # take-ok, take-out, boot power, buzzer, logo, language, backlight
R_M0_V, R_M0_I, R_M0_OVP, R_M0_OCP = 80, 81, 82, 83
R_PRESETS = range(80, 120)  # M0-M9: V, I, OVP, OCP each; M0 is the active set
RIDEN_SIZE = 120
RIDEN_WRITABLE = {R_V_SET, R_I_SET, R_LOCK, R_OUTPUT, R_PRESET, *R_CLOCK, *R_SETTINGS, *R_PRESETS}
RIDEN_OVP_DEFAULT_V = 62.0
"""Default OVP (V): above the 60 V range and representable at every model's resolution (the
RD6006P/RD6012P's 1 mV counts reach 65.535 V; 66 V would wrap to 0.464 V)."""
RIDEN_OCP_MARGIN_A = 0.2
"""Default OCP: the range's full scale plus this (A), 6.2 A on a 6 A range (62 000 counts)."""


class NoReply(Exception):  # noqa: N818 - what happens, not an error of ours
    """A silent device in simulated time: the request is never answered. The synchronous server
    (:mod:`sim.pipe_modbus`) drops it, as the asyncio server's handler, asleep for an hour,
    never answers it."""


async def _apply_faults(faults: Faults, simulated: bool = False) -> ExcCodes | None:
    """The device's own faults before it answers (``simulated``: the model runs on a simulated
    clock, where nothing may truly await: delays are ``timebase.sleep`` on it)."""
    if faults.silent:
        if simulated:
            raise NoReply
        await asyncio.sleep(3600.0)  # the client times out first
    if faults.reply_delay_s > 0:
        if simulated:
            timebase.sleep(faults.reply_delay_s)
        else:
            await asyncio.sleep(faults.reply_delay_s)
    if faults.exception_code:
        return ExcCodes(faults.exception_code)
    return None


def _write_words(address: int, values: Any, write: Callable[[int, list[int]], int],
                       ) -> ExcCodes | None:  # fmt: skip
    """Apply a write request's words through ``write(address, words)`` (words used, or an
    exception code's negative)."""
    words = list(values) if isinstance(values, list) else [values]
    pos = 0
    while pos < len(words):
        used = write(address + pos, words[pos:])
        if used < 0:
            return ExcCodes(-used)
        pos += used
    return None


class _Model:
    """A Modbus device model: faults first, then a read refreshes the registers from the physics
    and a write is checked and applied (:meth:`write`: words used, or an exception's negative)."""

    faults: Faults
    write_function: int = 6
    simulated: bool = False
    """Whether the model was built on a simulated clock (its fault delays then sleep on it)."""

    def refresh(self, regs: list[int], base: int) -> None:
        raise NotImplementedError

    def write(self, address: int, words: list[int]) -> int:
        raise NotImplementedError

    def writable(self, address: int, count: int) -> bool:
        """Whether a write of ``count`` words at ``address`` may start (checked before any is
        applied); by default each register is checked as it is written."""
        return True

    async def action(self, fc: int, start_address: int, address: int, count: int,
                     regs: list[int], values: Any) -> ExcCodes | None:  # fmt: skip
        """pymodbus' hook, run on every access before it answers."""
        fault = await _apply_faults(self.faults, self.simulated)
        if fault is not None:
            return fault
        if fc == WRITE_SINGLE and self.write_function == 16:
            return ExcCodes.ILLEGAL_FUNCTION  # a device without function 6 (the Maynuo M97xx)
        if fc == WRITE_SINGLE and values is None:
            return None  # pymodbus reading back the word just written: the reply echoes it
        if values is None or fc in READ_CODES:
            self.refresh(regs, start_address)
            return None
        if not self.writable(address, len(values) if isinstance(values, list) else 1):
            return ExcCodes.ILLEGAL_ADDRESS
        return _write_words(address, values, self.write)


class RidenModel(_Model):
    """A Riden RD60xx's registers (model from ``supply.cfg.model_id``) bound to ``supply``."""

    def __init__(self, supply: Supply, serial_number: int) -> None:
        self.supply, self.faults, self.serial_number = supply, supply.faults, serial_number
        self.simulated = timebase.is_simulated()
        self.model_id = supply.cfg.model_id
        self.spec = spec = riden_model(self.model_id)
        self.range = supply.cfg.current_range if len(spec.a_per_count) > 1 else 0
        self.writable_set = RIDEN_WRITABLE | ({R_I_RANGE} if len(spec.a_per_count) > 1 else set())
        self.stored: dict[int, int] = {R_CLOCK[0]: 2026, R_CLOCK[1]: 1, R_CLOCK[2]: 1,
                                       R_SETTINGS[-1]: 4}  # fmt: skip
        self.start = timebase.monotonic()
        self.default_protection()

    def i_lsb(self) -> float:
        """Current resolution of the present range (A per count)."""
        return self.spec.a_per_count[self.range]

    def i_max(self) -> float:
        """Full scale of the present range (A)."""
        return self.spec.i_max_a[self.range]

    def default_protection(self) -> None:
        """OVP and OCP as at power-on (or after a range change)."""
        self.supply.set_protection(
            RIDEN_OVP_DEFAULT_V, min(self.i_max() + RIDEN_OCP_MARGIN_A, 0xFFFF * self.i_lsb())
        )

    def words(self) -> dict[int, int]:
        """Every live register's value (address -> value, before wrapping to 16 bits)."""
        sup, v_lsb, i_lsb = self.supply, self.spec.v_per_count, self.i_lsb()
        with sup.lock:
            i_out, v_out = sup.output_current(), sup.output_voltage()
            temp_c = 28 + min(20.0, (timebase.monotonic() - self.start) / 600.0 * abs(i_out))
            power = round(v_out * i_out / self.spec.w_per_count)
            return {
                R_ID: self.model_id, R_SN_H: self.serial_number >> 16,
                R_SN_L: self.serial_number & 0xFFFF, R_FW: 140, R_TEMP_C: round(temp_c),
                R_TEMP_F: round(temp_c * 9 / 5 + 32), R_V_SET: round(sup.v_set / v_lsb),
                R_I_SET: round(sup.i_set / i_lsb), R_V_OUT: round(v_out / v_lsb),
                R_I_OUT: round(i_out / i_lsb), R_P_H: power >> 16, R_P_L: power & 0xFFFF,
                R_V_IN: round(sup.cfg.input_voltage_v * 100), R_PROTECT: sup.protection,
                R_CVCC: 1 if sup.cc_mode() else 0, R_OUTPUT: 1 if sup.output else 0,
                R_I_RANGE: self.range, **self.stored,
                R_M0_V: round(sup.v_set / v_lsb), R_M0_I: round(sup.i_set / i_lsb),  # M0: active
                R_M0_OVP: round(sup.ovp_v / v_lsb), R_M0_OCP: round(sup.ocp_a / i_lsb),
            }  # fmt: skip

    def refresh(self, regs: list[int], base: int) -> None:
        """The live registers into ``regs`` (holding addresses ``base`` onwards)."""
        for addr, value in self.words().items():
            if 0 <= addr - base < len(regs):
                regs[addr - base] = value & 0xFFFF

    def writable(self, address: int, count: int) -> bool:
        """Every register of the write is writable (else none is written: exception 2)."""
        return all(address + i in self.writable_set for i in range(count))

    def write(self, address: int, words: list[int]) -> int:
        """One register written (1), or a Modbus exception's negative."""
        try:
            refused = self._write(address, int(words[0]))
        except ValueError:
            return -ExcCodes.ILLEGAL_VALUE
        return 1 if refused is None else -refused

    def _write(self, addr: int, word: int) -> ExcCodes | None:
        sup, v_lsb, i_lsb = self.supply, self.spec.v_per_count, self.i_lsb()
        if addr in (R_V_SET, R_M0_V):
            if word * v_lsb > self.spec.v_max_v:
                return ExcCodes.ILLEGAL_VALUE
            sup.set_voltage(word * v_lsb)
        elif addr in (R_I_SET, R_M0_I):
            if word * i_lsb > self.i_max():
                return ExcCodes.ILLEGAL_VALUE
            sup.set_current(word * i_lsb)
        elif addr == R_OUTPUT:
            if word not in (0, 1):
                return ExcCodes.ILLEGAL_VALUE
            sup.set_output(bool(word))
        elif addr == R_M0_OVP:
            sup.set_protection(ovp_v=word * v_lsb)
        elif addr == R_M0_OCP:
            sup.set_protection(ocp_a=word * i_lsb)
        elif addr == R_I_RANGE:
            return self._set_range(word)
        else:
            self.stored[addr] = word
        return None

    def _set_range(self, word: int) -> ExcCodes | None:
        if word not in range(len(self.spec.a_per_count)):
            return ExcCodes.ILLEGAL_VALUE
        if word != self.range:  # the set-point in A is kept (capped at the new range)
            self.range = word
            if self.supply.i_set > self.i_max():
                self.supply.set_current(self.i_max())
            self.default_protection()
        return None


def riden_device(supply: Supply, device_id: int, serial_number: int = 12345) -> SimDevice:
    """A Riden RD60xx (model from ``supply.cfg.model_id``) on Modbus ``device_id``."""
    model = RidenModel(supply, serial_number)
    regs0 = [0] * RIDEN_SIZE
    model.refresh(regs0, 0)
    return SimDevice(
        id=device_id,
        simdata=[SimData(address=0, values=regs0, datatype=DataType.REGISTERS)],
        action=model.action,
    )


class RegmapModel(_Model):
    """A device described by a register map, bound to a supply/e-load, the polarity relays or
    (role ``temperature``) the DUT's temperature. Registers of role ``none`` keep what is written
    (their ``value`` at power-on); a register with ``mirror`` is the named register at a second
    address. A register the map lacks answers exception 2, or reads 0 where the map says the
    device does (``undefined_reads = "zero"``); a write to it answers exception 2. Coils
    (functions 1 and 5) are served from their own address space (:mod:`sim.regmap_coils`).

    A load whose map selects constant current (``RegisterMap.cc_select``) starts in the mode its
    ``mode`` register's ``value`` gives (the Maynuo: CV); a command to its output register other
    than on and off sets the mode's ``mask`` bits, and out of constant current it does not follow
    its current set-point: with its input on it sinks its full range (a load in CV at 0 V)."""

    PROTECTION_NAMES: ClassVar[dict[int, str]] = {1: "OVP", 2: "OCP", 3: "OPP"}

    def __init__(self, spec: RegisterMap, physics: CagePhysics, supply: Supply | None,
                 faults: Faults) -> None:  # fmt: skip
        self.spec, self.physics, self.supply, self.faults = spec, physics, supply, faults
        self.simulated = timebase.is_simulated()
        self.write_function = spec.write_function
        self.stored: dict[str, float] = {
            r.name: r.value for r in spec.registers if r.role != "constant" and r.value is not None
        }
        self.axis = None if supply is None else supply.cfg.axis
        self.by_address = {r.address: r for r in spec.registers if not r.is_coil}
        self.by_name = {r.name: r for r in spec.registers}
        self.coils = {r.address: r for r in spec.registers if r.is_coil}
        self.selects_cc = spec.cc_select() is not None
        if self.selects_cc and supply is not None:  # its power-on mode (the Maynuo: CV)
            self._follow_mode(supply)
        if supply is not None:  # protection defaults the registers can hold (never wrapped)
            ovp, ocp, opp = spec.role("ovp"), spec.role("ocp"), spec.role("opp")
            supply.set_protection(
                None if ovp is None else min(supply.ovp_v, ovp.limits()[1]),
                None if ocp is None else min(supply.ocp_a, ocp.limits()[1]),
                opp_w=None if opp is None else opp.value,  # the map's power-on OPP
            )

    def sign(self) -> float:
        """Output polarity of a bipolar coil supply (+1 otherwise)."""
        if self.spec.bipolar and self.axis is not None:
            return float(self.physics.bipolar_sign[self.axis])
        return 1.0

    def value_of(self, reg: Register) -> float:
        """What ``reg`` reads now (in its unit)."""
        if reg.mirror is not None:
            return self.value_of(self.by_name[reg.mirror])
        if reg.role == "constant":
            return reg.value or 0.0
        if reg.role == "model":  # its value, else the first code the map lists
            return reg.value if reg.value is not None else float(reg.models[0][0])
        if self.selects_cc and reg.role in ("mode", "i_set"):  # as written (the mode: commanded)
            return self.stored.get(reg.name, 0.0)
        if reg.role == "temperature":
            return self.physics.dut_temperature_c()
        if reg.role.startswith("polarity_"):
            return 1.0 if self.physics.relays.sign["xyz".index(reg.role[-1])] < 0 else 0.0
        if self.supply is None:
            return self.stored.get(reg.name, 0.0)
        getter = self._supply_getters(self.supply, reg).get(reg.role)
        return getter() if getter is not None else self.stored.get(reg.name, 0.0)

    def _supply_getters(self, sup: Supply, reg: Register) -> dict[str, Callable[[], float]]:
        on = 1.0 if sup.output else 0.0
        return {
            "v_set": lambda: sup.v_set,
            "i_set": lambda: self.sign() * sup.i_set,
            "v_out": lambda: self.sign() * sup.output_voltage(),
            "i_out": lambda: self.sign() * sup.output_current(),
            "power": sup.power_w,
            # an output register reads 1/0, or (a command register) the last command written
            "output": lambda: on if (reg.on, reg.off) == (1.0, 0.0)
            else self.stored.get(reg.name, reg.on if sup.output else reg.off),
            "output_state": lambda: on,
            "mode": lambda: 1.0 if sup.cc_mode() else 0.0,
            "protection": lambda: float(
                reg.protection_value(self.PROTECTION_NAMES.get(sup.protection, ""))),
            "ovp": lambda: sup.ovp_v,
            "ocp": lambda: sup.ocp_a,
            "opp": lambda: sup.opp_w or 0.0,
        }  # fmt: skip

    async def action(self, fc: int, start_address: int, address: int, count: int,
                     regs: list[int], values: Any) -> ExcCodes | None:  # fmt: skip
        """pymodbus' hook: coils here (exception 1 for the spaces no map describes, 2 for the
        holding registers of a map without any), the rest as every model does."""
        if not self.coils:
            return await super().action(fc, start_address, address, count, regs, values)
        if fc in BIT_ONLY_CODES or fc == 15:
            return ExcCodes.ILLEGAL_FUNCTION
        if fc not in COIL_CODES:
            if not self.by_address:
                return ExcCodes.ILLEGAL_ADDRESS
            return await super().action(fc, start_address, address, count, regs, values)
        fault = await _apply_faults(self.faults, self.simulated)
        if fault is not None:
            return fault
        if values is None:  # a read; for function 5 pymodbus reading the coil just written back
            if fc != 5:  # (the reply is an echo of the request)
                pack(regs, start_address, list(self.coils.values()), self.value_of)
            return None
        reg = self.coils.get(address)
        if reg is None or reg.access != "rw":
            return ExcCodes.ILLEGAL_ADDRESS
        try:
            self.apply(reg, 1.0 if values[0] else 0.0)
        except ValueError:
            return ExcCodes.ILLEGAL_VALUE
        return None

    def refresh(self, regs: list[int], base: int) -> None:
        """Every register's value into ``regs`` (holding addresses ``base`` onwards)."""
        for reg in self.by_address.values():
            for i, w in enumerate(reg.encode(self.value_of(reg), saturate=True)):
                if 0 <= reg.address + i - base < len(regs):
                    regs[reg.address + i - base] = w

    def write(self, address: int, words: list[int]) -> int:
        """The register at ``address`` written from ``words``: its width, or an exception's
        negative (not a writable register's start, or cut short: 2; a refused value: 3)."""
        reg = self.by_address.get(address)
        if reg is None or reg.access != "rw" or reg.width > len(words):
            return -ExcCodes.ILLEGAL_ADDRESS
        try:
            self.apply(reg, reg.decode(words[: reg.width]))
        except ValueError:
            return -ExcCodes.ILLEGAL_VALUE
        return reg.width

    def apply(self, reg: Register, value: float) -> None:
        """A written value to the physics (ValueError: refused)."""
        sup = self.supply
        if reg.mirror is not None:
            self.apply(self.by_name[reg.mirror], value)
        elif reg.role.startswith("polarity_"):
            if value not in (reg.on, reg.off):
                raise ValueError(f"relay command {value:g} is neither {reg.on:g} nor {reg.off:g}")
            self.physics.set_polarity("xyz".index(reg.role[-1]), -1 if value == reg.on else 1)
        elif self.selects_cc and sup is not None and reg.role in ("mode", "output", "i_set"):
            self._apply_load(sup, reg, value)
        elif sup is None or reg.role not in ("v_set", "i_set", "output", "ovp", "ocp", "opp"):
            self.stored[reg.name] = value
        elif reg.role == "v_set":
            sup.set_voltage(value)
        elif reg.role == "i_set":
            self._set_current(sup, value)
        elif reg.role == "output":
            if (reg.on, reg.off) == (1.0, 0.0) and value not in (0.0, 1.0):
                raise ValueError("output must be 0 or 1")
            if value in (reg.on, reg.off):
                sup.set_output(value == reg.on)
            self.stored[reg.name] = value  # a command register reads back the last command
        elif reg.role == "ovp":
            sup.set_protection(ovp_v=value)
        elif reg.role == "ocp":
            sup.set_protection(ocp_a=value)
        else:
            sup.set_protection(opp_w=value)

    def _apply_load(self, sup: Supply, reg: Register, value: float) -> None:
        """A write to a load that selects its mode: on/off and mode commands to the output
        register, a mode to a writable ``mode`` register, the current set-point; the physical
        set-point follows it only in constant current (else the load's full range)."""
        mode = self.spec.require("mode")
        if reg.role == "output":
            self.stored[reg.name] = value  # a command register reads back the last command
            if value in (reg.on, reg.off):
                sup.set_output(value == reg.on)
                return
        if reg.role in ("output", "mode"):  # a mode command: its bits in the mode register
            old = int(self.stored.get(mode.name, 0.0))
            self.stored[mode.name] = float((old & ~mode.mask) | (int(value) & mode.mask))
        elif not 0.0 <= value <= sup.i_max:
            raise ValueError(f"{value:g} A is outside 0-{sup.i_max:g} A")
        else:
            self.stored[reg.name] = value
        self._follow_mode(sup)

    def _follow_mode(self, sup: Supply) -> None:
        """The physical current set-point of a load that selects its mode: IFIX in constant
        current, else its full range (what it sinks with its input on)."""
        mode = self.spec.require("mode")
        ifix = self.stored.get(self.spec.require("i_set").name, 0.0)
        sup.set_current(ifix if mode.reads_cc(self.stored.get(mode.name, 0.0)) else sup.i_max)

    def _set_current(self, sup: Supply, value: float) -> None:
        if self.spec.bipolar and self.axis is not None:
            sup.set_current(abs(value))
            self.physics.set_bipolar_sign(self.axis, -1 if value < 0 else 1)
        elif value < 0:
            raise ValueError("this supply is unipolar: current set-point must be >= 0")
        else:
            sup.set_current(value)


def regmap_device(
    spec: RegisterMap, device_id: int, physics: CagePhysics, supply: Supply | None, faults: Faults
) -> SimDevice:
    """A device described by a register map (:class:`RegmapModel`) on Modbus ``device_id``."""
    model = RegmapModel(spec, physics, supply, faults)
    if spec.undefined_reads == "zero":  # every address readable: the unlisted ones read 0
        blocks = [SimData(address=0, count=65536, datatype=DataType.REGISTERS)]
    else:
        blocks = [
            SimData(address=r.address, values=r.encode(0.0), datatype=DataType.REGISTERS)
            for r in sorted(model.by_address.values(), key=lambda r: r.address)
        ]
    if model.coils:
        spaces = separate_spaces(blocks, list(model.coils.values()))
        return SimDevice(id=device_id, simdata=spaces, action=model.action)
    return SimDevice(id=device_id, simdata=blocks, action=model.action)


def unserved_ids() -> SimDevice:
    """pymodbus' catch-all device (id 0) for a Modbus TCP endpoint: a request for any unit id the
    endpoint does not serve is answered with exception 11, gateway target device failed to
    respond, as a Modbus TCP gateway does when nothing on its serial side answers that id
    (Modbus Application Protocol V1.1b3, section 7). Without it pymodbus 3.16 answers exception
    4, server device failure: its ``SimCore`` raises ``KeyError`` for an unknown id, and the
    server reports any error in the datastore as a device failure.

    Not for Modbus RTU: there a request for another id never reaches the server
    (:class:`sim.transports.PtyNullModem`, in simulated time :mod:`sim.pipe_modbus`, keeps the bus
    silent, as a real RS-485 device does)."""

    async def action(fc: int, start_address: int, address: int, count: int,
                     regs: list[int], values: Any) -> ExcCodes | None:  # fmt: skip
        return ExcCodes.GATEWAY_NO_RESPONSE

    every_address = SimData(address=0, count=65536, datatype=DataType.REGISTERS)
    return SimDevice(id=0, simdata=[every_address], action=action)


def _role(s: SupplyConfig) -> str:
    if s.trim is not None:
        return f"trim_{'xyz'[s.trim]}"
    return f"coil_{'xyz'[s.axis]}" if s.axis is not None else "load"


def _start_riden(host: CageHost, s: SupplyConfig, index: int) -> dict[str, Any]:
    """A Riden RD60xx (its register set, :func:`riden_device`) driving a coil or a load."""
    supply = host.physics.supplies[s.name]
    device = riden_device(supply, s.endpoint.device_id)
    entry = host.serve_modbus(s.name, device, s.endpoint, supply.faults)
    return entry | {"kind": "riden-rd60xx", "role": _role(s)}


def _start_regmap(host: CageHost, s: SupplyConfig, index: int) -> dict[str, Any]:
    """A supply or electronic load described by a register map (``regmap = "<name>"``)."""
    supply = host.physics.supplies[s.name]
    spec = load_regmap(s.regmap)
    if spec.kind == "eload":
        supply.set_voltage(min(s.input_voltage_v, supply.v_max))
    device = regmap_device(spec, s.endpoint.device_id, host.physics, supply, supply.faults)
    entry = host.serve_modbus(s.name, device, s.endpoint, supply.faults)
    return entry | {"kind": f"regmap-{spec.kind}", "regmap": spec.source, "role": _role(s)}


RIDEN = SimKind("riden-rd60xx", "supplies", _start_riden)
REGMAP = SimKind("regmap", "supplies", _start_regmap)
