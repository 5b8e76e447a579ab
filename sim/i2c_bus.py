"""The simulated I2C bus: an smbus2-compatible object (``i2c_rdwr``, the SMBus block and byte
helpers) carrying simulated register-level devices (:mod:`sim.rm3100`, :mod:`sim.lis3mdl`), with
the kernel's errors (errno 121 from an absent or silent device) and its 32-byte block limit."""

from __future__ import annotations

import ctypes
import errno
from typing import Any, Protocol

import timebase
from sim.physics import Faults

I2C_M_RD = 0x0001
"""The read flag of an i2c_msg (linux/i2c.h)."""


class BusDevice(Protocol):
    """A device on :class:`SimI2CBus`: its address, its faults, and register access (its
    ``_advance`` brings its conversions up to now before every transfer)."""

    address: int
    faults: Faults

    def _advance(self) -> None: ...

    def write(self, reg: int, data: bytes) -> None: ...

    def read(self, reg: int, length: int) -> bytes: ...


class SimI2CBus:
    """An smbus2-compatible bus object carrying simulated devices (``i2c_rdwr`` and friends)."""

    def __init__(self) -> None:
        self.devices: dict[int, BusDevice] = {}
        self._lock = timebase.Lock()

    def attach(self, device: BusDevice) -> None:
        """Put a device on the bus at its address."""
        self.devices[device.address] = device

    def _device(self, addr: int) -> BusDevice:
        dev = self.devices.get(addr)
        if dev is None or dev.faults.silent or dev.faults.disconnect:
            raise OSError(errno.EREMOTEIO, "Remote I/O error")  # errno 121, as the kernel
        return dev

    def i2c_rdwr(self, *msgs: Any) -> None:
        """Combined transfer: a register-address write, then reads or more writes."""
        with self._lock:
            pointer: int | None = None
            for msg in msgs:
                dev = self._device(int(msg.addr))
                dev._advance()
                if msg.flags & I2C_M_RD:
                    data = dev.read(pointer or 0, int(msg.len))
                    ctypes.memmove(msg.buf, data, int(msg.len))
                    pointer = (pointer or 0) + int(msg.len)
                else:
                    payload = ctypes.string_at(msg.buf, int(msg.len))
                    if not payload:
                        continue
                    pointer = payload[0]
                    if len(payload) > 1:
                        dev.write(pointer, payload[1:])
                        pointer += len(payload) - 1

    # SMBus block helpers (32-byte limit, as in the kernel)
    def read_i2c_block_data(
        self, addr: int, reg: int, length: int, force: bool | None = None
    ) -> list[int]:
        """SMBus block read."""
        if length > 32:
            raise ValueError("SMBus block reads are limited to 32 bytes")
        with self._lock:
            dev = self._device(addr)
            dev._advance()
            return list(dev.read(reg, length))

    def write_i2c_block_data(
        self, addr: int, reg: int, data: list[int], force: bool | None = None
    ) -> None:
        """SMBus block write."""
        with self._lock:
            dev = self._device(addr)
            dev._advance()
            dev.write(reg, bytes(data))

    def read_byte_data(self, addr: int, reg: int, force: bool | None = None) -> int:
        """SMBus byte read."""
        return self.read_i2c_block_data(addr, reg, 1)[0]

    def write_byte_data(self, addr: int, reg: int, value: int, force: bool | None = None) -> None:
        """SMBus byte write."""
        self.write_i2c_block_data(addr, reg, [value])

    def close(self) -> None:
        """Nothing to release (API compatibility)."""
