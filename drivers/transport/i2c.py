"""I2C register access on smbus2 (``/dev/i2c-N``) or any object with ``i2c_rdwr``."""

from __future__ import annotations

import errno
from typing import Any

from smbus2 import SMBus, i2c_msg

import timebase
from drivers.errors import DeviceNotFoundError, DeviceTimeoutError


class I2CDevice:
    """A device at ``address`` on ``bus`` (an int bus number, or an smbus2-compatible object)."""

    def __init__(
        self, bus: int | Any, address: int, *, name: str = "i2c", retries: int = 2
    ) -> None:
        self.name = name
        self.address = address
        self.retries = retries
        if isinstance(bus, int):
            try:
                self._bus: Any = SMBus(bus)
            except OSError as exc:
                raise DeviceNotFoundError(
                    f"{name}: cannot open /dev/i2c-{bus}: {exc.strerror}; check the bus number"
                ) from None
            self.where = f"/dev/i2c-{bus} 0x{address:02x}"
        else:
            self._bus = bus
            self.where = f"{type(bus).__name__} 0x{address:02x}"

    def _rdwr(self, *msgs: Any) -> None:
        for attempt in range(self.retries + 1):
            try:
                self._bus.i2c_rdwr(*msgs)
                return
            except OSError as exc:
                if (
                    exc.errno not in (errno.EREMOTEIO, errno.EIO, errno.ETIMEDOUT, errno.EAGAIN)
                    or attempt == self.retries
                ):
                    if exc.errno == errno.EREMOTEIO:
                        raise DeviceNotFoundError(
                            f"{self.name} at {self.where}: no acknowledge (NACK) after"
                            f" {attempt + 1} attempts; check the address, wiring and power"
                        ) from None
                    raise DeviceTimeoutError(
                        f"{self.name} at {self.where}: transfer failed ({exc})"
                    ) from None

    def read(self, register: int, length: int) -> bytes:
        """Write the register address, then read ``length`` bytes (repeated start)."""
        w, r = i2c_msg.write(self.address, [register]), i2c_msg.read(self.address, length)
        self._rdwr(w, r)
        return bytes(r)

    def wait_for_bit(
        self, register: int, mask: int, timeout_s: float, poll_s: float = 0.0005
    ) -> None:
        """Poll ``register`` until ``mask`` is set (data ready), or :class:`DeviceTimeoutError`."""
        deadline = timebase.monotonic() + timeout_s
        while not self.read(register, 1)[0] & mask:
            if timebase.monotonic() > deadline:
                raise DeviceTimeoutError(
                    f"{self.name} at {self.where}: no data ready within {timeout_s:g} s"
                    f" (register 0x{register:02x} bit mask 0x{mask:02x})"
                )
            timebase.sleep(poll_s)

    def write(self, register: int, data: bytes | list[int]) -> None:
        """Write ``data`` starting at ``register`` (auto-increment)."""
        self._rdwr(i2c_msg.write(self.address, [register, *bytes(data)]))
