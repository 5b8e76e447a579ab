"""Supplies, electronic loads, polarity relays and thermometers described by a register-map file."""

from __future__ import annotations

import dataclasses
import math

from drivers.errors import DeviceNotFoundError, DeviceProtocolError, LimitError
from drivers.identity import Identity
from drivers.protection import asked_levels, check_read_back
from drivers.protocols import ProtectionLevel, SupplyReading
from drivers.regmap import Register, RegisterMap, RegisterMapError
from drivers.transport.modbus import ModbusLink


class MappedDevice:
    """Common register access for map-described devices."""

    def __init__(self, link: ModbusLink, regmap: RegisterMap, name: str) -> None:
        self.link = link
        self.map = regmap
        self.name = name

    def _read(self, reg: Register) -> float:
        return reg.decode(self.link.read_registers(reg.address, reg.width))

    def _write(self, reg: Register, value: float) -> None:
        if reg.access != "rw":
            raise RegisterMapError(f"{self.map.source}: register '{reg.name}' is read-only")
        words = reg.encode(value)
        if len(words) == 1 and self.map.write_function == 6:
            self.link.write_register(reg.address, words[0])
        else:
            self.link.write_registers(reg.address, words)

    def close(self) -> None:
        """Close the Modbus link."""
        self.link.close()

    def check_model(self) -> None:
        """Read every ``constant`` register that states its value (the model register, say) and
        raise :class:`DeviceNotFoundError` if one differs: the device is not what the map says."""
        for reg in self.map.constants():
            got = self._read(reg)
            if got != reg.value:
                raise DeviceNotFoundError(
                    f"{self.name} at {self.link.where}: register '{reg.name}' ({reg.address:#06x})"
                    f" reads {got:g}, {self.map.source} expects {reg.value:g}; is this a"
                    f" {self.map.model}? Check the regmap and the device id"
                )

    def identify(self) -> Identity:
        """The map's model name, checked against the device's constant registers (the model
        register) where the map has them."""
        self.check_model()
        serial_reg = self.map.role("serial")
        serial = str(int(self._read(serial_reg))) if serial_reg else ""
        return Identity(self.map.model, serial, "")


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
        """Output (or load input) enable (the map's on/off values: 1/0, or a command)."""
        self._write(self.output_reg, self.output_reg.on if on else self.output_reg.off)

    def read(self) -> SupplyReading:
        """Set-points, measured output and power, protection (registers the map lacks read as 0;
        power as None)."""

        def get(role: str) -> float:
            reg = self.map.role(role)
            return self._read(reg) if reg is not None else 0.0

        prot = self.map.role("protection")
        protection = "" if prot is None else prot.protection_name(int(self._read(prot)))
        reading = SupplyReading(
            v_set_v=get("v_set"), i_set_a=get("i_set"), v_out_v=get("v_out"), i_out_a=get("i_out"),
            output_on=bool(get("output_state" if self.map.role("output_state") else "output")),
            constant_current=bool(get("mode")), protection=protection,
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
    """H-bridge relays, one per coil axis: 0 = normal, 1 = reversed.

    Switching a coil that carries current arcs the contacts; the cage controller brings the axis to
    zero before calling :meth:`set_polarity` (break before make).
    """

    def __init__(self, link: ModbusLink, regmap: RegisterMap, *, name: str = "polarity") -> None:
        if regmap.kind != "relay":
            raise RegisterMapError(f"{regmap.source}: kind '{regmap.kind}' is not a relay board")
        super().__init__(link, regmap, name)
        self.regs = [regmap.require(f"polarity_{ax}") for ax in "xyz"]

    def polarity(self, axis: int) -> int:
        """+1 (normal) or -1 (reversed)."""
        value = self._read(self.regs[axis])
        if value not in (0.0, 1.0):
            raise DeviceProtocolError(
                f"{self.name} at {self.link.where}: relay state {value:g} is not 0 or 1"
            )
        return -1 if value else 1

    def set_polarity(self, axis: int, sign: int) -> None:
        """Set axis ``axis`` (0-2) to ``sign`` (+1 or -1)."""
        self._write(self.regs[axis], 1.0 if sign < 0 else 0.0)

    def safe(self) -> None:
        """Every axis back to normal (0), the position a de-energised relay falls to. Call it only
        with the coils off (the cage controller and the guardian switch the supplies off and wait
        for the coil current to decay first)."""
        for reg in self.regs:
            self._write(reg, 0.0)


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
