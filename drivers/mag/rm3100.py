"""PNI RM3100 over I2C: cycle counts, single (POLL) and continuous (CMM) measurements, DRDY.

Plain register addresses over I2C (the manual's 0x80 read bit is SPI only). Results are 24-bit
two's complement, big-endian; gain = 0.3671 CC + 1.5 counts per uT (75 at CC = 200).

Continuous mode writes CMM = 0x79: START, CMX/CMY/CMZ, and DRDM = 10, "DRDY to HIGH after a full
measurement sequence is completed" (PNI RM3100 user manual, Table 5-3): a set of results every
time, whatever the alarm limits hold. DRDM = 00 (0x71, what ArduPilot and Firmament write) raises
DRDY when ALARM is 1 and the sequence is done; ALARM is 1 when an axis is above its upper or below
its lower limit (5.2.2), so with both limits at their power-on 0 any nonzero reading signals, but
a sensor whose limits were set around the field, or that reads 0 on every axis, never would.
"""

from __future__ import annotations

from typing import Any

from drivers.errors import DeviceNotFoundError
from drivers.identity import Identity
from drivers.mag.polled import PolledSampling
from drivers.transport.i2c import I2CDevice

POLL, CMM, CCX, TMRC, MX, STATUS, REVID = 0x00, 0x01, 0x04, 0x0B, 0x24, 0x34, 0x36
REVID_VALUE = 0x22
CMM_CONTINUOUS = 0x79
"""START (bit 0) | DRDM = 10 (bits 2-3: DRDY after each full X/Y/Z set) | CMX CMY CMZ (bits 4-6)."""
TMRC_HZ = {0x92: 600.0, 0x93: 300.0, 0x94: 150.0, 0x95: 75.0, 0x96: 37.0, 0x97: 18.0,
           0x98: 9.0, 0x99: 4.5, 0x9A: 2.3, 0x9B: 1.2, 0x9C: 0.6, 0x9D: 0.3}  # fmt: skip


def gain_counts_per_ut(cycle_count: int) -> float:
    """Counts per uT at a cycle count (PNI's linear fit)."""
    return 0.3671 * cycle_count + 1.5


def decode_results(raw: bytes, cycle_count: int) -> tuple[float, float, float]:
    """Nine result bytes (MX, MY, MZ) to uT."""
    g = gain_counts_per_ut(cycle_count)
    x, y, z = (int.from_bytes(raw[i : i + 3], "big", signed=True) / g for i in (0, 3, 6))
    return x, y, z


class Rm3100(PolledSampling):
    """An RM3100 at ``address`` (0x20-0x23) on ``bus`` (bus number or smbus2-compatible object)."""

    def __init__(self, bus: int | Any, address: int = 0x20, *, cycle_count: int = 200,
                 name: str = "RM3100") -> None:  # fmt: skip
        self.name = name
        self.dev = I2CDevice(bus, address, name=name)
        self.identify()
        self.cycle_count = 0
        self.set_cycle_count(cycle_count)
        self.continuous = False

    def identify(self) -> Identity:
        """Checks REVID = 0x22."""
        rev = self.dev.read(REVID, 1)[0]
        if rev != REVID_VALUE:
            raise DeviceNotFoundError(
                f"{self.name} at {self.dev.where}: REVID 0x{rev:02x}, expected 0x22; is it an RM3100?"
            )
        return Identity("RM3100", "", f"0x{rev:02x}")

    def set_cycle_count(self, cc: int) -> None:
        """Same cycle count on all axes (30-400 typical; higher = lower noise, slower)."""
        if not 1 <= cc <= 0xFFFF:
            raise ValueError(f"{self.name}: cycle count {cc} outside 1-65535")
        self.dev.write(CCX, list(cc.to_bytes(2, "big")) * 3)
        self.cycle_count = cc

    def read(self, timeout_s: float = 0.2) -> tuple[float, float, float]:
        """One measurement (uT): a POLL in single mode, the next result in continuous mode."""
        if not self.continuous:
            self.dev.write(POLL, [0x70])
        self.dev.wait_for_bit(STATUS, 0x80, timeout_s)  # DRDY
        return decode_results(self.dev.read(MX, 9), self.cycle_count)

    def start_continuous(self, tmrc: int = 0x96) -> float:
        """Continuous measurement at the TMRC rate (0x92-0x9D); returns the nominal rate (Hz)."""
        if tmrc not in TMRC_HZ:
            raise ValueError(f"{self.name}: TMRC 0x{tmrc:02x} outside 0x92-0x9D")
        self.dev.write(TMRC, [tmrc])
        self.dev.write(CMM, [CMM_CONTINUOUS])
        self.continuous = True
        return TMRC_HZ[tmrc]

    def close(self) -> None:
        """Nothing to release: the bus belongs to whoever opened it."""

    def stop_continuous(self) -> None:
        """Back to single measurements (writing CMM = 0)."""
        self.dev.write(CMM, [0x00])
        self.continuous = False
