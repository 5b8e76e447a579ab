"""ST LIS3MDL over I2C (address 0x1C or 0x1E): WHO_AM_I 0x3D, little-endian int16 outputs.

Multi-byte I2C reads set bit 7 of the sub-address for auto-increment (read from 0x28 | 0x80).
Sensitivity 6842 / 3421 / 2281 / 1711 LSB per gauss at +-4 / 8 / 12 / 16 G (1 G = 100 uT).
"""

from __future__ import annotations

from typing import Any

from drivers.errors import DeviceNotFoundError
from drivers.identity import Identity
from drivers.mag.polled import PolledSampling
from drivers.transport.i2c import I2CDevice

WHO_AM_I, CTRL_REG1, CTRL_REG2, CTRL_REG3, CTRL_REG4, STATUS, OUT_X_L = (
    0x0F, 0x20, 0x21, 0x22, 0x23, 0x27, 0x28,
)  # fmt: skip
WHO_AM_I_VALUE = 0x3D
AUTO_INCREMENT = 0x80
LSB_PER_GAUSS = {4: 6842.0, 8: 3421.0, 12: 2281.0, 16: 1711.0}


class Lis3mdl(PolledSampling):
    """Ultra-high-performance mode, 80 Hz, continuous conversion."""

    def __init__(self, bus: int | Any, address: int = 0x1C, *, full_scale_gauss: int = 4,
                 name: str = "LIS3MDL") -> None:  # fmt: skip
        if full_scale_gauss not in LSB_PER_GAUSS:
            raise ValueError(f"{name}: full scale must be one of {sorted(LSB_PER_GAUSS)} G")
        self.name = name
        self.dev = I2CDevice(bus, address, name=name)
        self.identify()
        self.lsb_per_ut = LSB_PER_GAUSS[full_scale_gauss] / 100.0
        fs_bits = {4: 0b00, 8: 0b01, 12: 0b10, 16: 0b11}[full_scale_gauss] << 5
        self.dev.write(CTRL_REG1, [0b0111_1100])  # OM = UHP (XY), DO = 80 Hz
        self.dev.write(CTRL_REG2, [fs_bits])
        self.dev.write(CTRL_REG4, [0b0000_1100])  # OMZ = UHP
        self.dev.write(CTRL_REG3, [0x00])  # continuous conversion

    def identify(self) -> Identity:
        """Checks WHO_AM_I = 0x3D."""
        who = self.dev.read(WHO_AM_I, 1)[0]
        if who != WHO_AM_I_VALUE:
            raise DeviceNotFoundError(
                f"{self.name} at {self.dev.where}: WHO_AM_I 0x{who:02x}, expected 0x3D"
            )
        return Identity("LIS3MDL", "", "")

    def read(self, timeout_s: float = 0.1) -> tuple[float, float, float]:
        """Next sample (uT) once ZYXDA (status bit 3) is set."""
        self.dev.wait_for_bit(STATUS, 0x08, timeout_s, poll_s=0.001)
        raw = self.dev.read(OUT_X_L | AUTO_INCREMENT, 6)
        x, y, z = (
            int.from_bytes(raw[i : i + 2], "little", signed=True) / self.lsb_per_ut
            for i in (0, 2, 4)
        )
        return x, y, z

    def close(self) -> None:
        """Nothing to release: the bus belongs to whoever opened it."""

    def safe(self) -> None:
        """Power-down mode."""
        self.dev.write(CTRL_REG3, [0x03])
