"""Supplies, electronic loads, polarity relays and thermometers described by a register-map file."""

from __future__ import annotations

import contextlib
import dataclasses
import math

from drivers.errors import (
    DeviceError,
    DeviceNotFoundError,
    DeviceProtocolError,
    DeviceStateError,
    LimitError,
)
from drivers.identity import Identity
from drivers.protection import asked_levels, check_read_back
from drivers.protocols import ProtectionLevel, SupplyReading
from drivers.transport.modbus import ModbusLink
from regmaps import Register, RegisterMap, RegisterMapError


class MappedDevice:
    """Common register access for map-described devices: holding registers (functions 3, 6 and
    16) and coils (1 and 5); remote control (role ``remote``) taken before the first write and
    given back on close."""

    def __init__(self, link: ModbusLink, regmap: RegisterMap, name: str) -> None:
        self.link = link
        self.map = regmap
        self.name = name
        self._remote = regmap.role("remote")
        self._remote_taken = False

    @property
    def where(self) -> str:
        """``name at port``, for messages."""
        return f"{self.name} at {self.link.where}"

    def _read(self, reg: Register) -> float:
        if reg.is_coil:
            return 1.0 if self.link.read_coils(reg.address, 1)[0] else 0.0
        return reg.decode(self.link.read_registers(reg.address, reg.width))

    def _write(self, reg: Register, value: float) -> None:
        if reg.access != "rw":
            raise RegisterMapError(f"{self.map.source}: register '{reg.name}' is read-only")
        if self._remote is not None and not self._remote_taken and reg is not self._remote:
            self._switch(self._remote, True)
            self._remote_taken = True
        words = reg.encode(value)
        if reg.is_coil:
            self.link.write_coil(reg.address, bool(words[0]))
        elif len(words) == 1 and self.map.write_function == 6:
            self.link.write_register(reg.address, words[0])
        else:
            self.link.write_registers(reg.address, words)

    def _state(self, reg: Register) -> bool:
        """A switched register's state as it reads: 1 on, 0 off (anything else: an error)."""
        value = self._read(reg)
        if value not in (0.0, 1.0):
            raise DeviceProtocolError(
                f"{self.where}: '{reg.name}' ({reg.address:#06x}) state {value:g} is not 0 or 1;"
                f" check that the regmap ({self.map.name}) is this device's"
            )
        return value == 1.0

    def _switch(self, reg: Register, on: bool) -> None:
        """Write ``reg``'s on or off value, then read its state back: DeviceStateError when it
        does not read what was written."""
        self._write(reg, reg.on if on else reg.off)
        if self._state(reg) != on:
            raise DeviceStateError(
                f"{self.where}: '{reg.name}' ({reg.address:#06x}) reads {'off' if on else 'on'}"
                f" after being switched {'on' if on else 'off'}; check the device's power and"
                " wiring, and that nothing else drives it"
            )

    def close(self) -> None:
        """Give remote control back (where it was taken; never raises), close the Modbus link."""
        if self._remote is not None and self._remote_taken:
            with contextlib.suppress(DeviceError):
                self._write(self._remote, self._remote.off)
            self._remote_taken = False
        self.link.close()

    def identify(self) -> Identity:
        """The model, checked against the map's constant registers and its model register
        (:meth:`RegisterMap.identify`): DeviceNotFoundError for another device; an unknown code
        of a family map is the family's model with a warning that names the code."""
        found = self.map.identify(self._read)
        if found.mismatch:
            raise DeviceNotFoundError(
                f"{self.where}: {found.mismatch}; is this a {self.map.model}? Check the regmap"
                " and the device id"
            )
        serial_reg = self.map.role("serial")
        serial = str(int(self._read(serial_reg))) if serial_reg else ""
        return Identity(found.model, serial, "", found.warning)


class MappedSupply(MappedDevice):
    """A supply or electronic load: current (and for supplies voltage) set-points, enable, readback.

    A bipolar supply takes a signed current; for the others negative set-points are refused.
    """

    def __init__(self, link: ModbusLink, regmap: RegisterMap, *, name: str = "supply",
                 max_voltage_v: float | None = None, max_current_a: float | None = None) -> None:  # fmt: skip
        if regmap.kind not in ("supply", "eload"):
            raise RegisterMapError(f"{regmap.source}: kind '{regmap.kind}' is not a supply or load")
        super().__init__(link, regmap, name)
        self.i_set_reg = regmap.require("i_set")
        self.output_reg = regmap.require("output")
        self.max_voltage_v = min(
            regmap.v_max, max_voltage_v if max_voltage_v is not None else regmap.v_max
        )
        self.max_current_a = min(
            regmap.i_max, max_current_a if max_current_a is not None else regmap.i_max
        )

    @property
    def bipolar(self) -> bool:
        """True when the current set-point is signed."""
        return self.map.bipolar

    @property
    def sets_voltage(self) -> bool:
        """True when the device has a voltage set-point (a supply; an electronic load has none:
        its input sees whatever the source across it gives, up to its range)."""
        return self.map.role("v_set") is not None

    def set_voltage(self, volts: float) -> float:
        """Voltage set-point (V), if the device has one."""
        reg = self.map.require("v_set")
        if not 0.0 <= volts <= self.max_voltage_v:
            raise LimitError(f"{self.name}: {volts:g} V is outside 0-{self.max_voltage_v:g} V")
        self._write(reg, volts)
        return volts

    def set_current(self, amps: float) -> float:
        """Current set-point (A); signed only for a bipolar supply."""
        low = -self.max_current_a if self.bipolar else 0.0
        if not low <= amps <= self.max_current_a:
            raise LimitError(f"{self.name}: {amps:g} A is outside {low:g}-{self.max_current_a:g} A")
        self._write(self.i_set_reg, amps)
        return amps

    def set_output(self, on: bool) -> None:
        """Output (or load input) enable (the map's on/off values: 1/0, or a command).

        Where the map says how constant current is selected (an electronic load: a load left in
        CV, CR or CW does not follow its current set-point), every switch-on first selects it and
        reads it back, and reads it again once on: a load that does not read constant current
        is not switched on, or is switched off again at once (DeviceStateError)."""
        out = self.output_reg
        select = self.map.cc_select()
        if not on or select is None:
            self._write(out, out.on if on else out.off)
            return
        reg, value = select
        self._write(reg, value)
        self._require_cc("before its input is switched on; the input stays off")
        self._write(out, out.on)
        try:
            self._require_cc("once its input was switched on; the input is switched off again")
        except DeviceStateError:
            with contextlib.suppress(DeviceError):
                self._write(out, out.off)
            raise

    def _require_cc(self, when: str) -> None:
        """DeviceStateError unless the ``mode`` register reads constant current."""
        mode = self.map.require("mode")
        raw = self._read(mode)
        if mode.reads_cc(raw):
            return
        shown = f"{int(raw):#06x}" if float(raw).is_integer() else f"{raw:g}"
        cc = int(1.0 if mode.cc is None else mode.cc)
        bits = f" under mask {mode.mask:#06x}" if mode.mask != 0xFFFF else ""
        raise DeviceStateError(
            f"{self.where}: does not read back constant current {when} ('{mode.name}' at"
            f" {mode.address:#06x} reads {shown}, CC reads {cc}{bits}): take it out of any"
            " program on its front panel (list, battery test, dynamic) and check the regmap's"
            f" cc values ({self.map.name})"
        )

    def read(self) -> SupplyReading:
        """Set-points, measured output and power, protection (registers the map lacks read as 0;
        power as None); constant current as the ``mode`` register says it (its ``cc``, ``mask``)."""

        def get(role: str) -> float:
            reg = self.map.role(role)
            return self._read(reg) if reg is not None else 0.0

        prot = self.map.role("protection")
        protection = "" if prot is None else prot.protection_name(int(self._read(prot)))
        mode = self.map.role("mode")
        reading = SupplyReading(
            v_set_v=get("v_set"), i_set_a=get("i_set"), v_out_v=get("v_out"), i_out_a=get("i_out"),
            output_on=bool(get("output_state" if self.map.role("output_state") else "output")),
            constant_current=mode is not None and mode.reads_cc(self._read(mode)),
            protection=protection,
        )  # fmt: skip
        power = self.map.role("power")
        if power is None:
            return reading
        return dataclasses.replace(reading, power_w=self._read(power))

    PROTECTION_ROLES = (("OVP", "ovp"), ("OCP", "ocp"), ("OPP", "opp"))
    """Each protection level and the map role of its register."""

    def protection_levels(self) -> tuple[ProtectionLevel, ...]:
        """The levels of the map's ``ovp`` (V), ``ocp`` (A) and ``opp`` (W) registers, read now."""
        return tuple(
            ProtectionLevel(kind, self._read(reg), f"register '{reg.name}' ({reg.address:#06x})")
            for kind, role in self.PROTECTION_ROLES
            if (reg := self.map.role(role)) is not None
        )

    def set_protection_levels(self, *, ovp_v: float | None = None, ocp_a: float | None = None,
                              opp_w: float | None = None) -> tuple[ProtectionLevel, ...]:  # fmt: skip
        """Write the levels given to the map's protection registers and read every level back
        (LimitError for one the map has no register for or that does not fit it)."""
        asked = asked_levels(self.name, ovp_v=ovp_v, ocp_a=ocp_a, opp_w=opp_w)
        regs = dict(self.PROTECTION_ROLES)
        writes = []
        for kind, value in asked.items():
            reg = self.map.role(regs[kind])
            if reg is None:
                raise LimitError(f"{self.name}: the {self.map.model} has no {kind} register in"
                                 f" {self.map.source}; leave its {kind} level out")  # fmt: skip
            if value > reg.limits()[1]:
                raise LimitError(f"{self.name}: {kind} {value:g} does not fit register"
                                 f" '{reg.name}' (at most {reg.limits()[1]:g})")  # fmt: skip
            writes.append((reg, value))
        for reg, value in writes:
            self._write(reg, value)
        levels = self.protection_levels()
        check_read_back(self.name, {kind: (value, _resolution(reg, value)) for (kind, value),
                                    (reg, _) in zip(asked.items(), writes, strict=True)},
                        levels)  # fmt: skip
        return levels

    def enable_as_load(self, compliance_v: float) -> None:
        """Drive a load harness: current 0, the voltage set-point (if the map has one) to the
        compliance voltage (capped at the device's range), output (or load input) on."""
        self.set_current(0.0)
        if self.map.role("v_set") is not None:
            self.set_voltage(min(compliance_v, self.max_voltage_v))
        self.set_output(True)

    def safe(self) -> None:
        """Output off, current set-point to zero."""
        self.set_output(False)
        self._write(self.i_set_reg, 0.0)


def _resolution(reg: Register, value: float) -> float:
    """One count of ``reg`` in its unit (a float32's: its relative precision at ``value``)."""
    return abs(value) * 1e-6 if reg.type == "float32" else 1.0 / reg.scale


class PolarityRelay(MappedDevice):
    """H-bridge relays, one per coil axis: off = normal, on = reversed (a coil, a register
    written 1/0, or one switched by command values such as 0x0100/0x0200); every switch is read
    back.

    Switching a coil that carries current arcs the contacts; the cage controller brings the axis to
    zero before calling :meth:`set_polarity` (break before make).
    """

    def __init__(self, link: ModbusLink, regmap: RegisterMap, *, name: str = "polarity") -> None:
        if regmap.kind != "relay":
            raise RegisterMapError(f"{regmap.source}: kind '{regmap.kind}' is not a relay board")
        super().__init__(link, regmap, name)
        self.regs = [regmap.require(f"polarity_{ax}") for ax in "xyz"]

    def polarity(self, axis: int) -> int:
        """+1 (normal) or -1 (reversed), as the relay reads."""
        return -1 if self._state(self.regs[axis]) else 1

    def set_polarity(self, axis: int, sign: int) -> None:
        """Set axis ``axis`` (0-2) to ``sign`` (+1 or -1) and read it back (DeviceStateError when
        the relay did not switch)."""
        self._switch(self.regs[axis], sign < 0)

    def safe(self) -> None:
        """Every axis back to normal (relay off, the position a de-energised relay falls to),
        each read back; every axis is tried before the first failure is raised. Call it only
        with the coils off (the cage controller and the guardian switch the supplies off and wait
        for the coil current to decay first)."""
        failed: list[DeviceError] = []
        for reg in self.regs:
            try:
                self._switch(reg, False)
            except DeviceError as exc:
                failed.append(exc)
        if failed:
            raise failed[0]


class MappedThermometer(MappedDevice):
    """A Modbus temperature module (an RTD or thermocouple input): one register with the role
    ``temperature``, in degrees C after the map's scale."""

    MIN_C, MAX_C = -200.0, 850.0
    """A reading outside this range (a PT100's span) is a broken or open sensor, not a
    temperature: modules report an open RTD as a sentinel such as -3276.8 or 3276.7."""

    def __init__(self, link: ModbusLink, regmap: RegisterMap, *, name: str = "thermometer") -> None:
        if regmap.kind != "thermometer":
            raise RegisterMapError(f"{regmap.source}: kind '{regmap.kind}' is not a thermometer")
        super().__init__(link, regmap, name)
        self.temperature_reg = regmap.require("temperature")

    def read_temperature_c(self) -> float:
        """The temperature (degrees C); DeviceProtocolError for an open or shorted sensor."""
        value = self._read(self.temperature_reg)
        if not (math.isfinite(value) and self.MIN_C <= value <= self.MAX_C):
            raise DeviceProtocolError(
                f"{self.name} at {self.link.where}: reads {value:g} degrees C, outside"
                f" {self.MIN_C:g} to {self.MAX_C:g}: is the sensor connected?"
            )
        return value
