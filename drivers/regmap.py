"""Register-map data files: a Modbus device described by its registers (TOML).

Format (shared with the simulator's models of the same devices)::

    [device]
    kind = "supply" | "eload" | "relay" | "thermometer"
    model = "..."
    v_max = 20.0            # V, supplies and loads
    i_max = 5.0             # A
    bipolar = false         # signed current set-point
    baudrate = 9600         # factory default on Modbus RTU (optional; 115200 when absent)

    [[registers]]
    name = "i_set"
    address = 0x0A01
    type = "uint16" | "int16" | "uint32" | "int32" | "float32"   # 32-bit: big-endian, high word first
    scale = 1000            # counts per unit (integer types)
    access = "ro" | "rw"
    role = "v_set" | "i_set" | "v_out" | "i_out" | "output" | "mode" | "protection"
         | "polarity_x" | "polarity_y" | "polarity_z" | "temperature" (degrees C)
         | "constant" | "none"
    value = 5005            # role "constant" only: what the register always reads (a model
                            # number): identify() and `rig devices scan` check it
"""

from __future__ import annotations

import struct
import tomllib
from dataclasses import dataclass
from pathlib import Path

MAP_DIR = Path(__file__).with_name("regmaps")
WIDTH = {"uint16": 1, "int16": 1, "uint32": 2, "int32": 2, "float32": 2}
MAP_KINDS = ("supply", "eload", "relay", "thermometer")


class RegisterMapError(ValueError):
    """A register-map file is malformed; the message names the file, entry and fix."""


@dataclass(frozen=True)
class Register:
    """One value: its address, encoding and role."""

    name: str
    address: int
    type: str
    access: str
    role: str
    scale: float = 1.0
    value: float | None = None  # role "constant": the value it always reads

    @property
    def width(self) -> int:
        """Number of 16-bit registers."""
        return WIDTH[self.type]

    def encode(self, value: float) -> list[int]:
        """Physical value to register words (raises ValueError if it does not fit)."""
        if self.type == "float32":
            return list(struct.unpack(">HH", struct.pack(">f", value)))
        counts = round(value * self.scale)
        lo, hi = {"uint16": (0, 0xFFFF), "int16": (-0x8000, 0x7FFF),
                  "uint32": (0, 0xFFFFFFFF), "int32": (-0x80000000, 0x7FFFFFFF)}[self.type]  # fmt: skip
        if not lo <= counts <= hi:
            raise ValueError(
                f"{value:g} does not fit register '{self.name}' ({self.type}, scale {self.scale:g})"
            )
        if self.width == 1:
            return [counts & 0xFFFF]
        c = counts & 0xFFFFFFFF
        return [c >> 16, c & 0xFFFF]

    def decode(self, words: list[int]) -> float:
        """Register words to the physical value."""
        if self.type == "float32":
            return float(struct.unpack(">f", struct.pack(">HH", *words))[0])
        c = words[0] if self.width == 1 else (words[0] << 16) | words[1]
        bits = 16 * self.width
        if self.type.startswith("int") and c & (1 << (bits - 1)):
            c -= 1 << bits
        return c / self.scale


@dataclass(frozen=True)
class RegisterMap:
    """A parsed map."""

    kind: str
    model: str
    registers: tuple[Register, ...]
    v_max: float
    i_max: float
    bipolar: bool
    source: str
    baudrate: int | None = None

    @property
    def name(self) -> str:
        """The map's file name without ``.toml`` (what ``regmap = "..."`` names)."""
        return Path(self.source).stem

    def constants(self) -> tuple[Register, ...]:
        """Registers that always read a stated value (the model number): the device's identity."""
        return tuple(r for r in self.registers if r.role == "constant" and r.value is not None)

    def role(self, role: str) -> Register | None:
        """The register with ``role``, if the map has one."""
        return next((r for r in self.registers if r.role == role), None)

    def require(self, role: str) -> Register:
        """The register with ``role``, or a RegisterMapError naming the file."""
        reg = self.role(role)
        if reg is None:
            raise RegisterMapError(f"{self.source}: no register with role '{role}'; add one")
        return reg


def find_map(name_or_path: str) -> Path:
    """A map by path, or by name among the shipped maps."""
    p = Path(name_or_path)
    if p.exists():
        return p
    shipped = MAP_DIR / (name_or_path if name_or_path.endswith(".toml") else f"{name_or_path}.toml")
    if shipped.exists():
        return shipped
    names = ", ".join(sorted(f.stem for f in MAP_DIR.glob("*.toml")))
    raise RegisterMapError(
        f"register map '{name_or_path}' not found; give a path or one of: {names}"
    )


def load_map(name_or_path: str) -> RegisterMap:
    """Parse and check a register map."""
    p = find_map(name_or_path)
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise RegisterMapError(f"{p}: not valid TOML ({exc})") from None
    dev = raw.get("device", {})
    regs = []
    for i, r in enumerate(raw.get("registers", [])):
        where = f"{p}: registers[{i}]"
        if r.get("type") not in WIDTH:
            raise RegisterMapError(f"{where}: type must be one of {', '.join(WIDTH)}")
        if r.get("access", "ro") not in ("ro", "rw"):
            raise RegisterMapError(f"{where}: access must be 'ro' or 'rw'")
        if "name" not in r or "address" not in r:
            raise RegisterMapError(f"{where}: needs a name and an address")
        regs.append(Register(str(r["name"]), int(r["address"]), str(r["type"]),
                             str(r.get("access", "ro")), str(r.get("role", "none")),
                             float(r.get("scale", 1.0)),
                             None if r.get("value") is None else float(r["value"])))  # fmt: skip
    kind = str(dev.get("kind", ""))
    if kind not in MAP_KINDS:
        raise RegisterMapError(f"{p}: [device] kind must be {', '.join(MAP_KINDS)}")
    baudrate = dev.get("baudrate")
    if baudrate is not None and (isinstance(baudrate, bool) or not isinstance(baudrate, int)):
        raise RegisterMapError(f"{p}: [device] baudrate must be a whole number, e.g. 9600")
    return RegisterMap(kind, str(dev.get("model", p.stem)), tuple(regs), float(dev.get("v_max", 0.0)),
                       float(dev.get("i_max", 0.0)), bool(dev.get("bipolar", False)), str(p),
                       baudrate)  # fmt: skip


def shipped_maps() -> list[RegisterMap]:
    """Every map in ``drivers/regmaps`` (sorted by name)."""
    return [load_map(str(f)) for f in sorted(MAP_DIR.glob("*.toml"))]
