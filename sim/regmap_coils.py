"""The coil space of a register-map device (``type = "coil"``: the Maynuo's remote and input
state, a relay board's relays) as pymodbus 3.16 serves it: a device with coils gets the four
separate spaces of the Modbus data model (coils, discrete inputs, holding and input registers)
instead of one shared block, so coil 0x0500 and register 0x0500 are different things, as on the
devices. Coils are packed 16 to a word there, bit 0 first (``SimDevice`` with bit addressing)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from pymodbus.simulator import DataType, SimData

from sim.regmap import Register

COIL_CODES = frozenset({1, 5, 15})
"""Read Coils, Write Single Coil, Write Multiple Coils."""
BIT_ONLY_CODES = frozenset({2, 4})
"""Discrete inputs and input registers: no map describes them (exception 1)."""


def separate_spaces(holding: list[SimData], coils: Sequence[Register]) -> tuple[Any, ...]:
    """``SimDevice.simdata`` for a device with ``coils``: (coils, discrete inputs, holding
    registers, input registers). pymodbus needs an entry in each space: the discrete inputs and
    input registers get a placeholder (the model answers exception 1 for them), and so do the
    holding registers of a map without any (the model answers exception 2 there)."""
    bits = [SimData(address=r.address, values=[False], datatype=DataType.BITS)
            for r in sorted(coils, key=lambda r: r.address)]  # fmt: skip
    placeholder = SimData(address=0, values=[0], datatype=DataType.REGISTERS)
    return (bits, [SimData(address=0, values=[False], datatype=DataType.BITS)],
            holding or [placeholder], [placeholder])  # fmt: skip


def pack(regs: list[int], base: int, coils: Sequence[Register],
         value_of: Callable[[Register], float]) -> None:  # fmt: skip
    """Each coil's state (``value_of``) into its bit of ``regs`` (packed words, word ``base`` at
    index 0: coil ``a`` is bit ``a % 16`` of word ``a // 16``)."""
    for reg in coils:
        i, bit = reg.address // 16 - base, reg.address % 16
        if 0 <= i < len(regs):
            on = value_of(reg) != 0.0
            regs[i] = (regs[i] | (1 << bit)) if on else (regs[i] & ~(1 << bit))
