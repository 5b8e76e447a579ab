"""ST LIS3MDL at register level on the simulated I2C bus (:class:`sim.i2c_bus.SimI2CBus`).

As the datasheet (DocID024204 Rev 6) gives it: WHO_AM_I (0x0F) reads 0x3D; a multi-byte transfer
auto-increments when bit 7 of the sub-address is set (5.1.1), and otherwise stays on its register,
except on the output registers: a read there moves through OUT_X_L..OUT_Z_H (0x28-0x2D) with or
without bit 7 and goes back to OUT_X_L after OUT_Z_H, as real parts do (a logic-analyzer trace in
PX4 issue 12514 of a read without bit 7; ST's community: "standard behavior"; the libraries that
read six bytes from 0x28 without it, Adafruit's and PX4's, get X, Y and Z). CTRL_REG1 DO (bits 4:2) sets the output
data rate (0.625 to 80 Hz; FAST_ODR, bit 1, 155 to 1000 Hz by the XY operating mode); CTRL_REG2
FS (bits 6:5) the full scale (6842 / 3421 / 2281 / 1711 LSB per gauss at +-4 / 8 / 12 / 16 G,
1 G = 100 uT); CTRL_REG3 MD (bits 1:0) the mode: 00 continuous, 01 single (one conversion, then
power-down), 1x power-down (the state at power-on). Outputs are int16 little-endian (saturated);
STATUS ZYXDA (bit 3) rises with each new set and falls when the outputs are read, ZYXOR (bit 7)
says a set was overwritten unread. Each conversion samples the field at its own time (ADR 0020).
The temperature sensor is not modelled (TEMP_OUT reads 0). A transfer while the device is silent
or disconnected raises ``OSError(121)`` on the bus, as the kernel does.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

import timebase
from sim.device_kind import CageHost, SimKind
from sim.physics import Faults

if TYPE_CHECKING:
    from sim.config import MagnetometerConfig

WHO_AM_I, CTRL_REG1, CTRL_REG2, CTRL_REG3, STATUS, OUT_X_L = 0x0F, 0x20, 0x21, 0x22, 0x27, 0x28
WHO_AM_I_VALUE = 0x3D
AUTO_INCREMENT = 0x80
OUTPUTS = range(OUT_X_L, OUT_X_L + 6)
"""OUT_X_L..OUT_Z_H: a read moves through them whatever bit 7 says, and wraps at the end."""
ZYXDA, ZYXOR = 0x08, 0x80
LSB_PER_GAUSS = (6842.0, 3421.0, 2281.0, 1711.0)  # by FS = 0..3
ODR_HZ = (0.625, 1.25, 2.5, 5.0, 10.0, 20.0, 40.0, 80.0)  # by DO = 0..7
FAST_ODR_HZ = (1000.0, 560.0, 300.0, 155.0)  # by OM (XY) = 0..3
READ_ONLY = {WHO_AM_I, STATUS, *range(OUT_X_L, 0x30)}


class Lis3mdl:
    """The device's registers and conversion timing; ``read_ut(t_s)`` is the field (uT) at
    device time ``t_s`` (monotonic s)."""

    def __init__(self, read_ut: Callable[[float], np.ndarray], faults: Faults,
                 address: int = 0x1C) -> None:  # fmt: skip
        self.read_ut = read_ut
        self.faults = faults
        self.address = address
        self.regs = bytearray(0x34)
        self.regs[WHO_AM_I] = WHO_AM_I_VALUE
        self.regs[CTRL_REG1] = 0x10  # DO = 100: 10 Hz
        self.regs[CTRL_REG3] = 0x03  # power-down
        self._since: float | None = None  # start of the present conversions (None: idle)
        self._last = 0  # conversions latched since then

    def odr_hz(self) -> float:
        """The output data rate CTRL_REG1 selects (Hz)."""
        c1 = self.regs[CTRL_REG1]
        return FAST_ODR_HZ[(c1 >> 5) & 3] if c1 & 0x02 else ODR_HZ[(c1 >> 2) & 7]

    def lsb_per_ut(self) -> float:
        """Counts per uT at the full scale CTRL_REG2 selects."""
        return LSB_PER_GAUSS[(self.regs[CTRL_REG2] >> 5) & 3] / 100.0

    def _restart(self) -> None:
        mode = self.regs[CTRL_REG3] & 0x03
        self._since = timebase.monotonic() if mode in (0, 1) else None
        self._last = 0

    def _latch(self, t_s: float, overwritten: bool) -> None:
        """The conversion that ended at ``t_s``: the field in the middle of it into the outputs
        (``overwritten``: sets came and went unread since the last latch)."""
        if self.faults.stuck and self.regs[STATUS] & ZYXDA:
            return
        field = np.asarray(self.read_ut(t_s - 0.5 / self.odr_hz()), dtype=float)
        for i in range(3):
            counts = max(-32768, min(32767, round(float(field[i]) * self.lsb_per_ut())))
            self.regs[OUT_X_L + 2 * i : OUT_X_L + 2 * i + 2] = counts.to_bytes(2, "little",
                                                                               signed=True)  # fmt: skip
        overrun = ZYXOR if overwritten or self.regs[STATUS] & ZYXDA else 0
        self.regs[STATUS] = (self.regs[STATUS] & ~(ZYXDA | ZYXOR)) | ZYXDA | overrun | 0x07

    def _advance(self) -> None:
        """Latch the conversions that ended by now (a single conversion powers down after)."""
        if self._since is None:
            return
        period = 1.0 / self.odr_hz()
        done = int((timebase.monotonic() - self._since) / period)
        if done <= self._last:
            return
        self._latch(self._since + done * period, done > self._last + 1)
        self._last = done
        if self.regs[CTRL_REG3] & 0x03 == 1:
            self.regs[CTRL_REG3] = (self.regs[CTRL_REG3] & ~0x03) | 0x03
            self._since = None

    def write(self, reg: int, data: bytes) -> None:
        """Register write (auto-increment when bit 7 of the sub-address is set)."""
        step = 1 if reg & AUTO_INCREMENT else 0
        reg &= 0x7F
        for offset, value in enumerate(data):
            r = reg + step * offset
            if r >= len(self.regs) or r in READ_ONLY:
                continue
            self.regs[r] = value
            if r in (CTRL_REG1, CTRL_REG3):
                self._restart()

    def read(self, reg: int, length: int) -> bytes:
        """Register read: auto-increment when bit 7 is set, and always through the output
        registers (wrapping from OUT_Z_H to OUT_X_L); reading the outputs clears ZYXDA."""
        increment = bool(reg & AUTO_INCREMENT)
        addrs = [reg & 0x7F][:length]
        while len(addrs) < length:
            a = addrs[-1]
            if a == OUTPUTS[-1]:
                addrs.append(OUTPUTS[0])
            else:
                addrs.append(a + 1 if increment or a in OUTPUTS else a)
        out = bytes(self.regs[a] if a < len(self.regs) else 0 for a in addrs)
        if any(a in OUTPUTS for a in addrs):
            self.regs[STATUS] = 0
        return out


def _start(host: CageHost, m: MagnetometerConfig, index: int) -> dict[str, Any]:
    """A LIS3MDL on the simulated I2C bus (``cage.i2c_bus``) at ``i2c_address`` (0x1C or 0x1E)."""
    if m.i2c_address not in (0x1C, 0x1E):
        raise ValueError(f"magnetometer '{m.name}': a LIS3MDL answers at 0x1C or 0x1E,"
                         f" not 0x{m.i2c_address:02X}: set i2c_address")  # fmt: skip
    host.add_i2c(m.name, Lis3mdl(host.field_reader(m.name),
                                 host.physics.magnetometers[m.name].faults, m.i2c_address))  # fmt: skip
    return {"kind": "lis3mdl", "protocol": "i2c", "bus": "sim", "address": m.i2c_address}


KIND = SimKind("lis3mdl", "magnetometers", _start)
