"""Riden RD60xx bench supplies over Modbus (RTU on USB-serial, or TCP through a bridge).

Register map and model-ID scaling after ShayBox/Riden and Baldanos/rd6006: holding registers
0 (model id), 1-2 (serial), 3 (firmware), 8 V_SET, 9 I_SET, 10 V_OUT, 11 I_OUT, 16 protection
(1 OVP, 2 OCP), 17 CV/CC (1 = CC), 18 output enable.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.errors import DeviceNotFoundError, LimitError
from drivers.identity import Identity
from drivers.transport.modbus import ModbusLink

MODELS: tuple[tuple[range, str, float, float, float, float], ...] = (
    # ids, name, V per count, A per count, V max, A max
    (range(60060, 60065), "RD6006", 0.01, 0.001, 60.0, 6.0),
    (range(60065, 60066), "RD6006P", 0.001, 0.0001, 60.0, 6.0),
    (range(60120, 60130), "RD6012", 0.01, 0.01, 60.0, 12.0),
    (range(60180, 60190), "RD6018", 0.01, 0.01, 60.0, 18.0),
)
REG_ID, REG_V_SET, REG_I_SET, REG_V_OUT, REG_I_OUT = 0, 8, 9, 10, 11
REG_PROTECT, REG_CVCC, REG_OUTPUT = 16, 17, 18


@dataclass(frozen=True)
class SupplyReading:
    """Set-points and measured output of a supply (V, A)."""

    v_set_v: float
    i_set_a: float
    v_out_v: float
    i_out_a: float
    output_on: bool
    constant_current: bool
    protection: str  # "", "OVP" or "OCP"


class RidenSupply:
    """One RD60xx channel. Limits: the model's range, narrowed by ``max_voltage_v``/``max_current_a``.

    Set-points are rounded to the model's resolution; the value actually set is returned.
    """

    bipolar = False
    """Riden supplies are unipolar: polarity comes from relays."""

    def __init__(self, link: ModbusLink, *, name: str = "riden", max_voltage_v: float | None = None,
                 max_current_a: float | None = None) -> None:  # fmt: skip
        self.link = link
        self.name = name
        model_id = link.read_registers(REG_ID, 1)[0]
        spec = next((m for m in MODELS if model_id in m[0]), None)
        if spec is None:
            raise DeviceNotFoundError(
                f"{name} at {link.where}: model id {model_id} is not a known Riden RD60xx;"
                " check the device id and that this is a Riden supply"
            )
        _, model, v_lsb, i_lsb, v_max, i_max = spec
        self.model, self.model_id = model, model_id
        self.v_lsb, self.i_lsb = v_lsb, i_lsb
        self.max_voltage_v = min(v_max, max_voltage_v if max_voltage_v is not None else v_max)
        self.max_current_a = min(i_max, max_current_a if max_current_a is not None else i_max)

    def identify(self) -> Identity:
        """Model, serial number and firmware version."""
        regs = self.link.read_registers(REG_ID, 4)
        return Identity(self.model, str((regs[1] << 16) | regs[2]), f"{regs[3] / 100:.2f}")

    def set_voltage(self, volts: float) -> float:
        """Voltage set-point (V); returns the value set after rounding to the resolution."""
        if not 0.0 <= volts <= self.max_voltage_v:
            raise LimitError(f"{self.name}: {volts:g} V is outside 0-{self.max_voltage_v:g} V")
        counts = round(volts / self.v_lsb)
        self.link.write_register(REG_V_SET, counts)
        return counts * self.v_lsb

    def set_current(self, amps: float) -> float:
        """Current limit (A); returns the value set after rounding to the resolution."""
        if not 0.0 <= amps <= self.max_current_a:
            raise LimitError(f"{self.name}: {amps:g} A is outside 0-{self.max_current_a:g} A")
        counts = round(amps / self.i_lsb)
        self.link.write_register(REG_I_SET, counts)
        return counts * self.i_lsb

    def set_output(self, on: bool) -> None:
        """Output enable."""
        self.link.write_register(REG_OUTPUT, 1 if on else 0)

    def read(self) -> SupplyReading:
        """Set-points, output and status in one request (registers 8-18)."""
        r = self.link.read_registers(REG_V_SET, 11)
        protection = {0: "", 1: "OVP", 2: "OCP"}.get(
            r[REG_PROTECT - 8], f"code {r[REG_PROTECT - 8]}"
        )
        return SupplyReading(
            v_set_v=r[0] * self.v_lsb,
            i_set_a=r[1] * self.i_lsb,
            v_out_v=r[2] * self.v_lsb,
            i_out_a=r[3] * self.i_lsb,
            output_on=bool(r[REG_OUTPUT - 8]),
            constant_current=bool(r[REG_CVCC - 8]),
            protection=protection,
        )

    def enable_as_load(self, compliance_v: float) -> None:
        """Drive a load harness: current 0, voltage to the compliance (capped), output on."""
        self.set_current(0.0)
        self.set_voltage(min(compliance_v, self.max_voltage_v))
        self.set_output(True)

    def safe(self) -> None:
        """Output off, then both set-points to zero (so a later enable cannot surprise anyone)."""
        self.set_output(False)
        self.link.write_register(REG_I_SET, 0)
        self.link.write_register(REG_V_SET, 0)

    def close(self) -> None:
        """Close the Modbus link (the output keeps its state: call :meth:`safe` first)."""
        self.link.close()
