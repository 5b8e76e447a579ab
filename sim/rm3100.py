"""PNI RM3100 at register level behind an smbus2-compatible object (``i2c_rdwr``).

Over I2C the register address is plain (the manual's 0x80 read bit is SPI only). Multi-byte
transfers auto-increment. Results are 24-bit two's complement, big-endian; the gain depends on the
cycle count (``0.3671 CC + 1.5`` counts per uT, 75 at the default CC = 200). A transfer to another
address, or any transfer while the NACK fault is on, raises ``OSError(121)`` like the kernel.

Mode bits as the PNI RM3100 user manual (Doc 1017252 r03/r04, section 5 and Tables 5-2 to 5-5)
gives them: POLL's PMX/PMY/PMZ (bits 4-6) choose the axes of a single measurement, whose end raises
DRDY. CMM: START (bit 0), ALARM (bit 1, the device's), DRDM (bits 2-3), CMX/CMY/CMZ (bits 4-6),
LDM (bit 7). In continuous mode DRDY follows DRDM (Table 5-3): 00 when ALARM is 1 and the chosen
axes' sequence is complete, 01 after a measurement on any axis, 10 after the chosen axes'
sequence, 11 when ALARM is 1; only the chosen axes' results are updated. ALARM (absolute mode,
5.2.2) is 1 when a measured axis is above its upper limit or below its lower limit (0x0C-0x1D,
24 bits each, power-on 0): with both limits at 0 any nonzero reading raises it, so CMM = 0x71
signals data ready as the flight stacks that write it (ArduPilot, Firmament) rely on. Relative
alarm mode (LDM = 1) is not modelled: its limits are taken as absolute.

Self test (BIST 0x33, 5.6.1): with STE (bit 7) set, a POLL runs the self test of the polled axes
instead of a measurement; its end raises DRDY and a healthy part reads XOK/YOK/ZOK (bits 4-6) = 1
for them (read-only bits, valid while STE is 1). BW (bits 2-3) and BP (bits 0-1) set its length.
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

POLL, CMM, CCX, CCY, CCZ, TMRC = 0x00, 0x01, 0x04, 0x06, 0x08, 0x0B
AXIS_BITS = (0x10, 0x20, 0x40)  # PMX/PMY/PMZ in POLL, CMX/CMY/CMZ in CMM
CMM_START, CMM_ALARM, CMM_DRDM = 0x01, 0x02, 0x0C
DRDM_ALARM_AND_ALL, DRDM_ANY_AXIS, DRDM_ALL_AXES, DRDM_ALARM = 0x00, 0x04, 0x08, 0x0C
ALARM_LIMITS = 0x0C
"""ALLX (lower), AULX (upper), ALLY, AULY, ALLZ, AULZ: 24-bit unsigned each, from 0x0C."""
BIST_STE, BIST_OK_SHIFT = 0x80, 4
BIST_WAIT_S = (30e-6, 30e-6, 60e-6, 120e-6)  # by BW (00 unused): sleep oscillation cycles
BIST_PERIODS = (1, 1, 2, 4)  # by BP (00 unused): LR periods per axis
MX, BIST, STATUS, HSHAKE, REVID = 0x24, 0x33, 0x34, 0x35, 0x36
REVID_VALUE = 0x22
TMRC_HZ = {0x92: 600.0, 0x93: 300.0, 0x94: 150.0, 0x95: 75.0, 0x96: 37.0, 0x97: 18.0,
           0x98: 9.0, 0x99: 4.5, 0x9A: 2.3, 0x9B: 1.2, 0x9C: 0.6, 0x9D: 0.3, 0x9E: 0.15,
           0x9F: 0.075}  # fmt: skip
SECONDS_PER_CYCLE = 1.0 / (430.0 * 3 * 200)  # manual: CC = 200 gives about 430 Hz for 3 axes


def gain_counts_per_ut(cycle_count: int) -> float:
    """Counts per uT for a cycle count (PNI's linear fit)."""
    return 0.3671 * cycle_count + 1.5


class Rm3100:
    """The device's registers and measurement timing."""

    def __init__(
        self, read_ut: Callable[[float], np.ndarray], faults: Faults, address: int = 0x20
    ) -> None:
        """``read_ut(t_s)``: the field (uT) at device time ``t_s`` (monotonic s)."""
        self.read_ut = read_ut
        self.faults = faults
        self.address = address
        self.regs = bytearray(0x40)
        for reg in (CCX, CCY, CCZ):
            self.regs[reg : reg + 2] = (200).to_bytes(2, "big")
        self.regs[TMRC] = 0x96
        self.regs[REVID] = REVID_VALUE
        self.regs[HSHAKE] = 0x1B
        self._ready_at: float | None = None  # completion time of a pending single measurement
        self._poll_axes = 0x70  # the PMX/PMY/PMZ bits of the pending single measurement
        self._self_test = False  # the pending POLL is a self test (BIST's STE was set)
        self._continuous_since: float | None = None
        self._last_cont_index = -1
        self._lock = timebase.Lock()

    def cycle_counts(self) -> tuple[int, int, int]:
        """CCX, CCY, CCZ."""
        return tuple(int.from_bytes(self.regs[r : r + 2], "big") for r in (CCX, CCY, CCZ))  # type: ignore[return-value]

    def _conversion_s(self) -> float:
        return sum(self.cycle_counts()) * SECONDS_PER_CYCLE

    def _measure(self, done_s: float, axes: int, drdy: bool) -> None:
        """Latch the reading of the conversion that completed at ``done_s`` (device time s) into
        the results of ``axes`` (bits 4-6) and, if ``drdy``, raise DRDY. The chosen axes convert
        one after another (x, y, z), each for its cycle count: each axis reads the field at the
        middle of its own conversion (at the default CC = 200, x 1.55 ms before z)."""
        if self.faults.stuck and self.regs[STATUS] & 0x80:
            return
        chosen = [(i, cc) for i, cc in enumerate(self.cycle_counts()) if axes & AXIS_BITS[i]]
        t = done_s - sum(cc for _, cc in chosen) * SECONDS_PER_CYCLE
        for i, cc in chosen:
            t += cc * SECONDS_PER_CYCLE
            value = float(self.read_ut(t - 0.5 * cc * SECONDS_PER_CYCLE)[i])
            counts = round(value * gain_counts_per_ut(cc))
            counts = max(-(1 << 23), min((1 << 23) - 1, counts)) & 0xFFFFFF
            self.regs[MX + 3 * i : MX + 3 * i + 3] = counts.to_bytes(3, "big")
        if drdy:
            self.regs[STATUS] |= 0x80

    def _alarm(self, axes: int) -> bool:
        """Absolute alarm mode (manual 5.2.2): a measured axis above its upper limit or below its
        lower limit (the limits unsigned, the results two's complement)."""
        for i in range(3):
            if not axes & AXIS_BITS[i]:
                continue
            value = int.from_bytes(self.regs[MX + 3 * i : MX + 3 * i + 3], "big", signed=True)
            lower, upper = (int.from_bytes(self.regs[r : r + 3], "big")
                            for r in (ALARM_LIMITS + 6 * i, ALARM_LIMITS + 6 * i + 3))  # fmt: skip
            if value > upper or value < lower:
                return True
        return False

    def _continuous_drdy(self, alarm: bool) -> bool:
        """Whether a continuous-mode sequence raises DRDY (manual Table 5-3, DRDM)."""
        drdm = self.regs[CMM] & CMM_DRDM
        if drdm in (DRDM_ALARM_AND_ALL, DRDM_ALARM):
            return alarm
        return drdm == DRDM_ANY_AXIS or bool(self.regs[CMM] & 0x70)

    def _continuous(self, done_s: float) -> None:
        """The continuous-mode sequence that completed at ``done_s``: results, ALARM, DRDY."""
        axes = self.regs[CMM] & 0x70
        self._measure(done_s, axes, drdy=False)
        alarm = self._alarm(axes)
        self.regs[CMM] = (self.regs[CMM] & ~CMM_ALARM) | (CMM_ALARM if alarm else 0)
        if self._continuous_drdy(alarm):
            self.regs[STATUS] |= 0x80

    def _bist_s(self) -> float:
        """The self test's length: BP LR periods per polled axis, each within BW's wait."""
        b = self.regs[BIST]
        axes = sum(1 for bit in AXIS_BITS if self._poll_axes & bit)
        return axes * BIST_PERIODS[b & 0x03] * BIST_WAIT_S[(b >> 2) & 0x03]

    def _advance(self) -> None:
        now = timebase.monotonic()
        if self._ready_at is not None and now >= self._ready_at:
            done_s, self._ready_at = self._ready_at, None
            if self._self_test:  # a healthy part: every tested axis's oscillator works
                self.regs[BIST] |= self._poll_axes & 0x70
                self.regs[STATUS] |= 0x80
            else:
                self._measure(done_s, self._poll_axes, drdy=True)
        if self._continuous_since is not None:
            rate = min(TMRC_HZ.get(self.regs[TMRC], 37.0), 1.0 / self._conversion_s())
            index = int((now - self._continuous_since) * rate)
            if index > self._last_cont_index:
                self._last_cont_index = index
                self._continuous(self._continuous_since + index / rate)

    def write(self, reg: int, data: bytes) -> None:
        """Register write with auto-increment."""
        for offset, value in enumerate(data):
            r = reg + offset
            if r >= len(self.regs):
                return
            if r == POLL:
                if value & 0x70:
                    self.regs[STATUS] &= 0x7F
                    self._poll_axes = value & 0x70
                    self._self_test = bool(self.regs[BIST] & BIST_STE)
                    took = self._bist_s() if self._self_test else self._conversion_s()
                    self._ready_at = timebase.monotonic() + took
            elif r == BIST:
                self.regs[BIST] = value & ~0x70  # XOK/YOK/ZOK are the device's: a new test
            elif r == CMM:
                self.regs[CMM] = value & ~CMM_ALARM  # ALARM is the device's
                if value & CMM_START:
                    self._continuous_since = timebase.monotonic()
                    self._last_cont_index = 0
                else:
                    self._continuous_since = None
            elif r == TMRC:
                self.regs[TMRC] = value
                self._continuous_since = None  # writing TMRC terminates continuous mode
            elif r in (REVID, STATUS) or MX <= r < MX + 9:
                continue  # read-only
            else:
                self.regs[r] = value

    def read(self, reg: int, length: int) -> bytes:
        """Register read with auto-increment; reading the results clears DRDY. BIST's OK bits
        read 0 while STE is 0 (the manual: the reading is then invalid)."""
        out = bytes(self.regs[reg : reg + length]).ljust(length, b"\x00")
        if reg <= BIST < reg + length and not self.regs[BIST] & BIST_STE:
            out = out[: BIST - reg] + bytes([self.regs[BIST] & ~0x70]) + out[BIST - reg + 1 :]
        if reg <= CMM < reg + length:
            self._continuous_since = None  # reading CMM terminates continuous mode
        if reg < MX + 9 and reg + length > MX:
            self.regs[STATUS] &= 0x7F
        return out


def _start(host: CageHost, m: MagnetometerConfig, index: int) -> dict[str, Any]:
    """An RM3100 on the simulated I2C bus (``cage.i2c_bus``) at ``i2c_address``."""
    host.add_i2c(m.name, Rm3100(host.field_reader(m.name),
                                host.physics.magnetometers[m.name].faults, m.i2c_address))  # fmt: skip
    return {"kind": "rm3100", "protocol": "i2c", "bus": "sim", "address": m.i2c_address}


KIND = SimKind("rm3100", "magnetometers", _start)
