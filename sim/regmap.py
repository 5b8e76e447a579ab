"""Register maps of Modbus devices described by a data file (TOML), and their value encoding.

A map lists registers with an address, a type (``uint16``, ``int16``, ``uint32``, ``int32``,
``float32``; 32-bit values big-endian, high word first), an access (``ro``/``rw``), a ``scale``
(counts per unit, integer types only) and a ``role`` that ties it to the physics
(``v_set``, ``i_set``, ``v_out``, ``i_out``, ``output``, ``mode``, ``protection``,
``polarity_x|y|z``, ``temperature`` (the DUT's, degrees C), ``constant`` or ``none``).
"""

from __future__ import annotations

import itertools
import struct
import tomllib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from sim.config import REGMAP_DIR, SimConfigError

TYPES = {"uint16": 1, "int16": 1, "uint32": 2, "int32": 2, "float32": 2}
ROLES = {
    "v_set", "i_set", "v_out", "i_out", "output", "mode", "protection",
    "polarity_x", "polarity_y", "polarity_z", "temperature", "constant", "none",
}  # fmt: skip
KINDS = ("supply", "eload", "relay", "thermometer")


@dataclass(frozen=True)
class Register:
    """One value in the map (1 or 2 Modbus registers)."""

    name: str
    address: int
    type: str
    access: str
    role: str
    scale: float = 1.0
    value: float = 0.0

    @property
    def width(self) -> int:
        """Number of 16-bit registers."""
        return TYPES[self.type]

    def encode(self, value: float) -> list[int]:
        """Physical value to register words."""
        if self.type == "float32":
            hi, lo = struct.unpack(">HH", struct.pack(">f", value))
            return [hi, lo]
        counts = round(value * self.scale)
        if self.type == "uint16":
            return [max(0, min(0xFFFF, counts))]
        if self.type == "int16":
            return [max(-0x8000, min(0x7FFF, counts)) & 0xFFFF]
        if self.type == "uint32":
            c = max(0, min(0xFFFFFFFF, counts))
            return [c >> 16, c & 0xFFFF]
        c = max(-0x80000000, min(0x7FFFFFFF, counts)) & 0xFFFFFFFF
        return [c >> 16, c & 0xFFFF]

    def decode(self, words: list[int]) -> float:
        """Register words to the physical value."""
        if self.type == "float32":
            return float(struct.unpack(">f", struct.pack(">HH", words[0], words[1]))[0])
        if self.type == "uint16":
            return words[0] / self.scale
        if self.type == "int16":
            w = words[0]
            return (w - 0x10000 if w & 0x8000 else w) / self.scale
        c = (words[0] << 16) | words[1]
        if self.type == "int32" and c & 0x80000000:
            c -= 1 << 32
        return c / self.scale


@dataclass(frozen=True)
class RegMap:
    """A device's register map."""

    kind: str  # one of KINDS
    model: str
    registers: tuple[Register, ...]
    v_max: float = 0.0
    i_max: float = 0.0
    source: str = ""
    bipolar: bool = False  # signed current set-point and readback (four-quadrant supply)

    def by_role(self, role: str) -> Register | None:
        """The register playing ``role``, if any."""
        return next((r for r in self.registers if r.role == role), None)


def resolve(path: str) -> Path:
    """A map file by path, or by name in ``sim/regmaps``."""
    p = Path(path)
    if p.exists():
        return p
    candidate = REGMAP_DIR / (path if path.endswith(".toml") else f"{path}.toml")
    if candidate.exists():
        return candidate
    raise SimConfigError(f"register map '{path}' not found (give a path or a name in {REGMAP_DIR})")


@lru_cache(maxsize=32)
def load_regmap(path: str) -> RegMap:
    """Parse and check a register-map file."""
    p = resolve(path)
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise SimConfigError(f"{p}: not valid TOML: {exc}") from None
    dev = raw.get("device", {})
    regs = []
    for i, r in enumerate(raw.get("registers", [])):
        where = f"{p.name}: registers[{i}]"
        if r.get("type") not in TYPES:
            raise SimConfigError(f"{where}.type must be one of {', '.join(TYPES)}")
        if r.get("role", "none") not in ROLES:
            raise SimConfigError(f"{where}.role must be one of {', '.join(sorted(ROLES))}")
        if r.get("access", "ro") not in ("ro", "rw"):
            raise SimConfigError(f"{where}.access must be 'ro' or 'rw'")
        regs.append(
            Register(
                name=str(r["name"]),
                address=int(r["address"]),
                type=str(r["type"]),
                access=str(r.get("access", "ro")),
                role=str(r.get("role", "none")),
                scale=float(r.get("scale", 1.0)),
                value=float(r.get("value", 0.0)),
            )
        )
    spans = sorted((r.address, r.address + r.width, r.name) for r in regs)
    for (_, a1, n0), (b0, _, n1) in itertools.pairwise(spans):
        if b0 < a1:
            raise SimConfigError(f"{p.name}: registers '{n0}' and '{n1}' overlap at {b0}")
    kind = str(dev.get("kind", "supply"))
    if kind not in KINDS:
        raise SimConfigError(f"{p.name}: device.kind must be one of {', '.join(KINDS)}")
    return RegMap(
        kind, str(dev.get("model", p.stem)), tuple(regs),
        float(dev.get("v_max", 0.0)), float(dev.get("i_max", 0.0)), str(p),
        bool(dev.get("bipolar", False)),
    )  # fmt: skip
