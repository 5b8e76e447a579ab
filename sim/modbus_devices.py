"""Modbus device models (pymodbus 3.16 ``SimDevice`` with an async action) bound to the physics.

The action runs on every access before pymodbus answers: reads refresh the live registers from
the physics; writes are checked and applied to the physics (or refused with a Modbus exception).
A Modbus TCP endpoint also answers for the unit ids it does not serve (:func:`unserved_ids`).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any

from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from sim.device_kind import CageHost, SimKind
from sim.physics import CagePhysics, Faults, Supply, riden_model
from sim.regmap import Register, RegisterMap, load_regmap

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


async def _apply_faults(faults: Faults) -> ExcCodes | None:
    if faults.silent:
        await asyncio.sleep(3600.0)  # the client times out first
    if faults.reply_delay_s > 0:
        await asyncio.sleep(faults.reply_delay_s)
    if faults.exception_code:
        return ExcCodes(faults.exception_code)
    return None


def riden_device(supply: Supply, device_id: int, serial_number: int = 12345) -> SimDevice:
    """A Riden RD60xx (model from ``supply.cfg.model_id``) on Modbus ``device_id``."""
    model_id = supply.cfg.model_id
    spec = riden_model(model_id)
    v_lsb, w_lsb = spec.v_per_count, spec.w_per_count
    state = {"range": supply.cfg.current_range if len(spec.a_per_count) > 1 else 0}
    writable = RIDEN_WRITABLE | ({R_I_RANGE} if len(spec.a_per_count) > 1 else set())
    stored: dict[int, int] = {R_CLOCK[0]: 2026, R_CLOCK[1]: 1, R_CLOCK[2]: 1, R_SETTINGS[-1]: 4}
    start = time.monotonic()

    def i_lsb() -> float:
        return spec.a_per_count[state["range"]]

    def i_max() -> float:
        return spec.i_max_a[state["range"]]

    def default_protection() -> None:
        supply.set_protection(
            RIDEN_OVP_DEFAULT_V, min(i_max() + RIDEN_OCP_MARGIN_A, 0xFFFF * i_lsb())
        )

    default_protection()

    def refresh(regs: list[int], base: int) -> None:
        def put(addr: int, value: int) -> None:
            if 0 <= addr - base < len(regs):
                regs[addr - base] = value & 0xFFFF

        with supply.lock:
            i_out = supply.output_current()
            v_out = supply.output_voltage()
            put(R_ID, model_id)
            put(R_SN_H, serial_number >> 16)
            put(R_SN_L, serial_number & 0xFFFF)
            put(R_FW, 140)
            temp_c = 28 + min(20.0, (time.monotonic() - start) / 600.0 * abs(i_out))
            put(R_TEMP_C, round(temp_c))
            put(R_TEMP_F, round(temp_c * 9 / 5 + 32))
            put(R_V_SET, round(supply.v_set / v_lsb))
            put(R_I_SET, round(supply.i_set / i_lsb()))
            put(R_V_OUT, round(v_out / v_lsb))
            put(R_I_OUT, round(i_out / i_lsb()))
            power = round(v_out * i_out / w_lsb)
            put(R_P_H, power >> 16)
            put(R_P_L, power & 0xFFFF)
            put(R_V_IN, round(supply.cfg.input_voltage_v * 100))
            put(R_PROTECT, supply.protection)
            put(R_CVCC, 1 if supply.cc_mode() else 0)
            put(R_OUTPUT, 1 if supply.output else 0)
            put(R_I_RANGE, state["range"])
            for addr, value in stored.items():
                put(addr, value)
            put(R_M0_V, round(supply.v_set / v_lsb))  # M0 is the active set
            put(R_M0_I, round(supply.i_set / i_lsb()))
            put(R_M0_OVP, round(supply.ovp_v / v_lsb))
            put(R_M0_OCP, round(supply.ocp_a / i_lsb()))

    def write(addr: int, word: int) -> ExcCodes | None:
        if addr in (R_V_SET, R_M0_V):
            if word * v_lsb > spec.v_max_v:
                return ExcCodes.ILLEGAL_VALUE
            supply.set_voltage(word * v_lsb)
        elif addr in (R_I_SET, R_M0_I):
            if word * i_lsb() > i_max():
                return ExcCodes.ILLEGAL_VALUE
            supply.set_current(word * i_lsb())
        elif addr == R_OUTPUT:
            if word not in (0, 1):
                return ExcCodes.ILLEGAL_VALUE
            supply.set_output(bool(word))
        elif addr == R_M0_OVP:
            supply.set_protection(ovp_v=word * v_lsb)
        elif addr == R_M0_OCP:
            supply.set_protection(ocp_a=word * i_lsb())
        elif addr == R_I_RANGE:
            if word not in range(len(spec.a_per_count)):
                return ExcCodes.ILLEGAL_VALUE
            if word != state["range"]:  # the set-point in A is kept (capped at the new range)
                state["range"] = word
                if supply.i_set > i_max():
                    supply.set_current(i_max())
                default_protection()
        else:
            stored[addr] = word
        return None

    async def action(fc: int, start_address: int, address: int, count: int,
                     regs: list[int], values: Any) -> ExcCodes | None:  # fmt: skip
        fault = await _apply_faults(supply.faults)
        if fault is not None:
            return fault
        if fc == WRITE_SINGLE and values is None:
            return None  # pymodbus reading back the word just written: the reply echoes it
        if values is None or fc in READ_CODES:
            refresh(regs, start_address)
            return None
        words = list(values) if isinstance(values, list) else [values]
        if any(address + i not in writable for i in range(len(words))):
            return ExcCodes.ILLEGAL_ADDRESS
        for offset, word in enumerate(words):
            try:
                result = write(address + offset, int(word))
            except ValueError:
                return ExcCodes.ILLEGAL_VALUE
            if result is not None:
                return result
        return None

    regs0 = [0] * RIDEN_SIZE
    refresh(regs0, 0)
    return SimDevice(
        id=device_id,
        simdata=[SimData(address=0, values=regs0, datatype=DataType.REGISTERS)],
        action=action,
    )


def regmap_device(
    spec: RegisterMap, device_id: int, physics: CagePhysics, supply: Supply | None, faults: Faults
) -> SimDevice:
    """A device described by a register map, bound to a supply/e-load, the polarity relays or
    (role ``temperature``) the DUT's temperature. Registers of role ``none`` keep what is written
    (their ``value`` at power-on); a register the map lacks answers exception 2."""
    stored: dict[str, float] = {
        r.name: r.value for r in spec.registers if r.role != "constant" and r.value is not None
    }
    axis = None if supply is None else supply.cfg.axis
    if supply is not None:  # protection defaults the registers can hold (never wrapped)
        ovp, ocp = spec.role("ovp"), spec.role("ocp")
        supply.set_protection(
            None if ovp is None else min(supply.ovp_v, ovp.limits()[1]),
            None if ocp is None else min(supply.ocp_a, ocp.limits()[1]),
        )
    protection_names = {1: "OVP", 2: "OCP"}

    def sign() -> float:
        """Output polarity of a bipolar coil supply (+1 otherwise)."""
        if spec.bipolar and axis is not None:
            return float(physics.bipolar_sign[axis])
        return 1.0

    def protection(reg: Register) -> float:
        assert supply is not None
        return float(reg.protection_value(protection_names.get(supply.protection, "")))

    def output_reads(reg: Register) -> float:
        """An output register reads 1/0, or (a command register) the last command written."""
        assert supply is not None
        if (reg.on, reg.off) == (1.0, 0.0):
            return 1.0 if supply.output else 0.0
        return stored.get(reg.name, reg.on if supply.output else reg.off)

    def value_of(reg: Register) -> float:
        if reg.role == "constant":
            return reg.value or 0.0
        if reg.role == "temperature":
            return physics.dut_temperature_c()
        if reg.role.startswith("polarity_"):
            return 1.0 if physics.relays.sign["xyz".index(reg.role[-1])] < 0 else 0.0
        if supply is None:
            return stored.get(reg.name, 0.0)
        getters: dict[str, Callable[[], float]] = {
            "v_set": lambda: supply.v_set,
            "i_set": lambda: sign() * supply.i_set,
            "v_out": lambda: sign() * supply.output_voltage(),
            "i_out": lambda: sign() * supply.output_current(),
            "power": lambda: supply.power_w(),
            "output": lambda: output_reads(reg),
            "output_state": lambda: 1.0 if supply.output else 0.0,
            "mode": lambda: 1.0 if supply.cc_mode() else 0.0,
            "protection": lambda: protection(reg),
            "ovp": lambda: supply.ovp_v,
            "ocp": lambda: supply.ocp_a,
        }
        return getters[reg.role]() if reg.role in getters else stored.get(reg.name, 0.0)

    def refresh(regs: list[int], base: int) -> None:
        for reg in spec.registers:
            words = reg.encode(value_of(reg), saturate=True)
            for i, w in enumerate(words):
                if 0 <= reg.address + i - base < len(regs):
                    regs[reg.address + i - base] = w

    def apply(reg: Register, value: float) -> None:
        if reg.role.startswith("polarity_"):
            physics.set_polarity("xyz".index(reg.role[-1]), -1 if value else 1)
        elif reg.role == "v_set" and supply is not None:
            supply.set_voltage(value)
        elif reg.role == "i_set" and supply is not None:
            if spec.bipolar and axis is not None:
                supply.set_current(abs(value))
                physics.set_bipolar_sign(axis, -1 if value < 0 else 1)
            elif value < 0:
                raise ValueError("this supply is unipolar: current set-point must be >= 0")
            else:
                supply.set_current(value)
        elif reg.role == "output" and supply is not None:
            if (reg.on, reg.off) == (1.0, 0.0) and value not in (0.0, 1.0):
                raise ValueError("output must be 0 or 1")
            if value in (reg.on, reg.off):
                supply.set_output(value == reg.on)
            stored[reg.name] = value  # a command register reads back the last command
        elif reg.role == "ovp" and supply is not None:
            supply.set_protection(ovp_v=value)
        elif reg.role == "ocp" and supply is not None:
            supply.set_protection(ocp_a=value)
        else:
            stored[reg.name] = value

    by_address = {r.address: r for r in spec.registers}

    async def action(fc: int, start_address: int, address: int, count: int,
                     regs: list[int], values: Any) -> ExcCodes | None:  # fmt: skip
        fault = await _apply_faults(faults)
        if fault is not None:
            return fault
        if fc == WRITE_SINGLE and spec.write_function == 16:
            return ExcCodes.ILLEGAL_FUNCTION  # a device without function 6 (the Maynuo M97xx)
        if fc == WRITE_SINGLE and values is None:
            return None  # pymodbus reading back the word just written: the reply echoes it
        if values is None or fc in READ_CODES:
            refresh(regs, start_address)
            return None
        words = list(values) if isinstance(values, list) else [values]
        pos = 0
        while pos < len(words):
            reg = by_address.get(address + pos)
            if reg is None or reg.access != "rw" or pos + reg.width > len(words):
                return ExcCodes.ILLEGAL_ADDRESS
            try:
                apply(reg, reg.decode(words[pos : pos + reg.width]))
            except ValueError:
                return ExcCodes.ILLEGAL_VALUE
            pos += reg.width
        return None

    blocks = [
        SimData(address=r.address, values=r.encode(0.0), datatype=DataType.REGISTERS)
        for r in sorted(spec.registers, key=lambda r: r.address)
    ]
    return SimDevice(id=device_id, simdata=blocks, action=action)


def unserved_ids() -> SimDevice:
    """pymodbus' catch-all device (id 0) for a Modbus TCP endpoint: a request for any unit id the
    endpoint does not serve is answered with exception 11, gateway target device failed to
    respond, as a Modbus TCP gateway does when nothing on its serial side answers that id
    (Modbus Application Protocol V1.1b3, section 7). Without it pymodbus 3.16 answers exception
    4, server device failure: its ``SimCore`` raises ``KeyError`` for an unknown id, and the
    server reports any error in the datastore as a device failure.

    Not for Modbus RTU: there a request for another id never reaches the server
    (:class:`sim.links.PtyNullModem` keeps the bus silent, as a real RS-485 device does)."""

    async def action(fc: int, start_address: int, address: int, count: int,
                     regs: list[int], values: Any) -> ExcCodes | None:  # fmt: skip
        return ExcCodes.GATEWAY_NO_RESPONSE

    every_address = SimData(address=0, count=65536, datatype=DataType.REGISTERS)
    return SimDevice(id=0, simdata=[every_address], action=action)


def _role(s: SupplyConfig) -> str:
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
