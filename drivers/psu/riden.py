"""Riden RD60xx bench supplies over Modbus (RTU on USB-serial, or TCP through a bridge).

Holding registers (ShayBox/Riden ``register.py``, Baldanos/rd6006 ``registers.md``, the
riden-dongle firmware's ``riden_modbus_registers.h``): 0 model id, 1-2 serial, 3 firmware
(x100), 8 V_SET, 9 I_SET, 10 V_OUT, 11 I_OUT, 12-13 power, 14 V_IN, 16 protection
(1 OVP, 2 OCP), 17 CV/CC (1 = CC), 18 output enable, 20 current range (RD6012P only), 82-83 the
active preset's OVP and OCP. Power is one 32-bit count, register 12 the high word (a real RD6030
read through register 13 alone wrapped at 655.36 W; ShayBox and libsigrok read 13 alone:
docs/devices.md weighs the sources).

Every model id and scale in :data:`MODELS` is one that the published tables list (see
docs/devices.md): ShayBox/Riden ``riden.py``, libsigrok's ``rdtech-dps`` model table and the
riden-dongle firmware. An id none of them lists is refused, never guessed.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.errors import DeviceNotFoundError, DeviceProtocolError, LimitError
from drivers.identity import Identity
from drivers.protection import asked_levels, check_read_back
from drivers.protocols import ProtectionLevel, SupplyReading
from drivers.transport.modbus import ModbusLink

REG_ID, REG_V_SET, REG_I_SET, REG_V_OUT, REG_I_OUT, REG_P_H = 0, 8, 9, 10, 11, 12
REG_PROTECT, REG_CVCC, REG_OUTPUT, REG_I_RANGE = 16, 17, 18, 20
REG_OVP, REG_OCP = 82, 83
"""M0 OVP and OCP: the active preset's protection levels, at the V and A set-points' scales."""


@dataclass(frozen=True)
class CurrentRange:
    """One current range of a model: resolution (A per count) and full scale (A)."""

    a_per_count: float
    i_max_a: float


@dataclass(frozen=True)
class RidenModel:
    """One RD60xx model: the ids register 0 reads, and its scales.

    ``ranges`` has one entry, or (RD6012P) one per value of register 20: the current range the
    front panel selects changes the current resolution, so the driver reads it.
    """

    name: str
    ids: tuple[int, ...]
    v_per_count: float
    w_per_count: float
    ranges: tuple[CurrentRange, ...]
    v_max_v: float = 60.0

    @property
    def range_dependent(self) -> bool:
        """True when register 20 selects the current resolution (RD6012P)."""
        return len(self.ranges) > 1


def _ids(first: int, last: int) -> tuple[int, ...]:
    return tuple(range(first, last + 1))


MODELS: tuple[RidenModel, ...] = (
    RidenModel("RD6006", _ids(60060, 60064), 0.01, 0.01, (CurrentRange(0.001, 6.0),)),
    RidenModel("RD6006P", (60065,), 0.001, 0.001, (CurrentRange(0.0001, 6.0),)),
    RidenModel("RK6006", (60066,), 0.01, 0.01, (CurrentRange(0.001, 6.0),)),
    RidenModel("RD6012", _ids(60120, 60124), 0.01, 0.01, (CurrentRange(0.01, 12.0),)),
    RidenModel(  # register 20: 0 = the 6 A range (0.1 mA), 1 = the 12 A range (1 mA)
        "RD6012P",
        _ids(60125, 60129),
        0.001,
        0.001,
        (CurrentRange(0.0001, 6.0), CurrentRange(0.001, 12.0)),
    ),
    RidenModel("RD6018", _ids(60180, 60189), 0.01, 0.01, (CurrentRange(0.01, 18.0),)),
    RidenModel("RD6024", _ids(60240, 60244), 0.01, 0.01, (CurrentRange(0.01, 24.0),)),
    RidenModel("RD6030", _ids(60300, 60304), 0.01, 0.01, (CurrentRange(0.01, 30.0),)),
)
"""The RD60xx family as the published tables give it (docs/devices.md names each source)."""


def riden_model(model_id: int) -> RidenModel | None:
    """The model register 0 names, or None for an id no published table lists."""
    return next((m for m in MODELS if model_id in m.ids), None)


def unknown_model_message(where: str, model_id: int) -> str:
    """One line: the id is not a known RD60xx, and what to do."""
    known = ", ".join(f"{m.name} {m.ids[0]}" + (f"-{m.ids[-1]}" if len(m.ids) > 1 else "")
                      for m in MODELS)  # fmt: skip
    return (
        f"{where}: model id {model_id} is not a known Riden RD60xx (known: {known}); check the"
        " device id and that this is a Riden supply, or add the model to drivers/psu/riden.py"
        " with its source"
    )


class RidenSupply:
    """One RD60xx channel. Limits: the model's range, narrowed by ``max_voltage_v``/``max_current_a``.

    Set-points are rounded to the model's resolution; the value actually set is returned. On an
    RD6012P the current resolution follows register 20 (the range chosen on the front panel):
    the driver reads it when it opens, before every current set-point and in every
    :meth:`read`, so a range change never scales a current by 10. ``current_range`` (0 or 1),
    when given, is written to register 20 at open.
    """

    bipolar = False
    """Riden supplies are unipolar: polarity comes from relays."""

    def __init__(self, link: ModbusLink, *, name: str = "riden", max_voltage_v: float | None = None,
                 max_current_a: float | None = None, current_range: int | None = None) -> None:  # fmt: skip
        self.link = link
        self.name = name
        model_id = link.read_registers(REG_ID, 1)[0]
        spec = riden_model(model_id)
        if spec is None:
            raise DeviceNotFoundError(unknown_model_message(f"{name} at {link.where}", model_id))
        self.spec, self.model, self.model_id = spec, spec.name, model_id
        self.v_lsb = spec.v_per_count
        self._v_counts = round(1.0 / spec.v_per_count)  # counts per V: values are counts / this
        self._limit_v, self._limit_a = max_voltage_v, max_current_a
        self.current_range = 0
        if current_range is not None and not spec.range_dependent:
            raise LimitError(
                f"{name} at {link.where}: current_range applies to the RD6012P only, this is an"
                f" {spec.name} (model id {model_id}); remove current_range from its configuration"
            )
        if current_range is not None:  # the configured range, written and read back
            self._set_range(current_range)
            link.write_register(REG_I_RANGE, current_range)
        if spec.range_dependent:
            self._set_range(link.read_registers(REG_I_RANGE, 1)[0])

    def _set_range(self, code: int) -> None:
        if not 0 <= code < len(self.spec.ranges):
            raise DeviceProtocolError(
                f"{self.name} at {self.link.where}: {self.model} current range (register 20)"
                f" reads {code}, expected 0-{len(self.spec.ranges) - 1}; check the firmware"
            )
        self.current_range = code

    @property
    def i_lsb(self) -> float:
        """Current resolution (A per count) in the present range."""
        return self.spec.ranges[self.current_range].a_per_count

    @property
    def _i_counts(self) -> int:
        """Counts per A in the present range (values are counts divided by it, so 1000 counts
        of 1 mA read 1.0 exactly)."""
        return round(1.0 / self.i_lsb)

    @property
    def max_voltage_v(self) -> float:
        """Highest voltage set-point (V): the model's, narrowed by the configuration."""
        v_max = self.spec.v_max_v
        return min(v_max, self._limit_v if self._limit_v is not None else v_max)

    @property
    def max_current_a(self) -> float:
        """Highest current set-point (A) in the present range, narrowed by the configuration."""
        i_max = self.spec.ranges[self.current_range].i_max_a
        return min(i_max, self._limit_a if self._limit_a is not None else i_max)

    def identify(self) -> Identity:
        """Model, serial number and firmware version."""
        regs = self.link.read_registers(REG_ID, 4)
        return Identity(self.model, str((regs[1] << 16) | regs[2]), f"{regs[3] / 100:.2f}")

    def set_voltage(self, volts: float) -> float:
        """Voltage set-point (V); returns the value set after rounding to the resolution."""
        if not 0.0 <= volts <= self.max_voltage_v:
            raise LimitError(f"{self.name}: {volts:g} V is outside 0-{self.max_voltage_v:g} V")
        counts = round(volts * self._v_counts)
        self.link.write_register(REG_V_SET, counts)
        return counts / self._v_counts

    def set_current(self, amps: float) -> float:
        """Current limit (A); returns the value set after rounding to the resolution."""
        if self.spec.range_dependent:
            self._set_range(self.link.read_registers(REG_I_RANGE, 1)[0])
        if not 0.0 <= amps <= self.max_current_a:
            raise LimitError(f"{self.name}: {amps:g} A is outside 0-{self.max_current_a:g} A")
        counts = round(amps * self._i_counts)
        self.link.write_register(REG_I_SET, counts)
        return counts / self._i_counts

    def set_output(self, on: bool) -> None:
        """Output enable."""
        self.link.write_register(REG_OUTPUT, 1 if on else 0)

    def read(self) -> SupplyReading:
        """Set-points, output, power and status in one request (registers 8-18; 8-20 on an
        RD6012P, whose range register scales the currents of the same reply)."""
        last = REG_I_RANGE if self.spec.range_dependent else REG_OUTPUT
        r = self.link.read_registers(REG_V_SET, last - REG_V_SET + 1)
        if self.spec.range_dependent:
            self._set_range(r[REG_I_RANGE - REG_V_SET])
        code = r[REG_PROTECT - REG_V_SET]
        p = (r[REG_P_H - REG_V_SET] << 16) | r[REG_P_H + 1 - REG_V_SET]
        return SupplyReading(
            v_set_v=r[0] / self._v_counts,
            i_set_a=r[1] / self._i_counts,
            v_out_v=r[2] / self._v_counts,
            i_out_a=r[3] / self._i_counts,
            output_on=bool(r[REG_OUTPUT - REG_V_SET]),
            constant_current=bool(r[REG_CVCC - REG_V_SET]),
            protection={0: "", 1: "OVP", 2: "OCP"}.get(code, f"code {code}"),
            power_w=p / round(1.0 / self.spec.w_per_count),
        )

    def protection_levels(self) -> tuple[ProtectionLevel, ...]:
        """OVP (V) and OCP (A) of the active preset M0 (registers 82-83); an RD60xx has no OPP."""
        if self.spec.range_dependent:
            self._set_range(self.link.read_registers(REG_I_RANGE, 1)[0])
        ovp, ocp = self.link.read_registers(REG_OVP, 2)
        return (ProtectionLevel("OVP", ovp / self._v_counts, f"register {REG_OVP} (M0 OVP)"),
                ProtectionLevel("OCP", ocp / self._i_counts, f"register {REG_OCP} (M0 OCP)"))  # fmt: skip

    def set_protection_levels(self, *, ovp_v: float | None = None, ocp_a: float | None = None,
                              opp_w: float | None = None) -> tuple[ProtectionLevel, ...]:  # fmt: skip
        """Write M0 OVP (V) and/or OCP (A) at the model's (and range's) resolution, then read
        both back. LimitError for an OPP (the RD60xx has none) or a level beyond 65535 counts."""
        asked = asked_levels(self.name, ovp_v=ovp_v, ocp_a=ocp_a, opp_w=opp_w)
        if "OPP" in asked:
            raise LimitError(f"{self.name}: the {self.model} has no over-power protection; leave"
                             " its OPP level out")  # fmt: skip
        if self.spec.range_dependent:
            self._set_range(self.link.read_registers(REG_I_RANGE, 1)[0])
        scales = {"OVP": (REG_OVP, self._v_counts), "OCP": (REG_OCP, self._i_counts)}
        for kind, value in asked.items():
            register, per_unit = scales[kind]
            if round(value * per_unit) > 0xFFFF:
                raise LimitError(f"{self.name}: {kind} {value:g} is beyond the {self.model}'s"
                                 f" register {register} ({0xFFFF / per_unit:g} at most)")  # fmt: skip
        for kind, value in asked.items():
            register, per_unit = scales[kind]
            self.link.write_register(register, round(value * per_unit))
        levels = self.protection_levels()
        check_read_back(self.name, {k: (v, 1.0 / scales[k][1]) for k, v in asked.items()}, levels)
        return levels

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
