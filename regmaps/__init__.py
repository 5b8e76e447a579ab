"""Register maps of Modbus devices (TOML files in this folder) and the one parser that reads them,
for the drivers and the simulator alike (docs/adr/0019-one-register-map-directory.md).

Format::

    [device]
    kind = "supply" | "eload" | "relay" | "thermometer"
    model = "..."
    v_max = 20.0            # V, supplies and loads
    i_max = 5.0             # A
    bipolar = false         # signed current set-point
    baudrate = 9600         # factory default on Modbus RTU (optional; 115200 when absent)
    write_function = 16     # 16: every write is Write Multiple Registers (a device without
                            # function 6); 6 (default): one register by 6, wider ones by 16
    undefined_reads = "zero"  # what a read of an address the map does not list answers on the
                            # real device: "zero" (it reads 0) or "exception" (exception 2,
                            # the default); the simulator answers the same

    [[registers]]
    name = "i_set"
    address = 0x0A01
    type = "uint16" | "int16" | "uint32" | "int32" | "float32"   # 32-bit: big-endian, high word first
    scale = 1000            # counts per unit (integer types)
    unit = "A"              # documentation only
    access = "ro" | "rw"
    role = one of ROLES (below)
    value = 5005            # role "constant": what the register always reads (a model number,
                            # checked by identify() and `rig devices scan`); other roles: the
                            # value it reads at power-on in the simulator
    codes = ["", "OVP", "OCP"]   # role "protection", a code per value (this is the default), or
    flags = ["OVP", "OCP"]       # role "protection", one bit each (bit 0 first)
    on = 42                 # role "output" written as a command: the values for on and off (the
    off = 43                # state is then read from a register of role "output_state")
    mirror = "v_set"        # this address is a second one of the named register: it reads and
                            # writes the same value (a DPS's 0x50, the active preset's U-SET)

An unknown key, role, kind, type or access is an error naming the file, the line and the nearest
valid name; so are overlapping registers, two registers of one name or role, an address outside
0-65535, a scale or limit that is not a finite number above 0 and a map of more than
:data:`MAX_REGISTERS` registers (:func:`parse_map`, issue 51). The parse takes time linear in the
number of registers (``bench/bench_regmap_parse.py``).
"""

from __future__ import annotations

import bisect
import difflib
import itertools
import math
import re
import struct
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

MAP_DIR = Path(__file__).parent
TYPES = {"uint16": 1, "int16": 1, "uint32": 2, "int32": 2, "float32": 2}
KINDS = ("supply", "eload", "relay", "thermometer")
ACCESS = ("ro", "rw")
ROLES = {
    "v_set": "voltage set-point (V)",
    "i_set": "current set-point (A)",
    "v_out": "measured output voltage (V)",
    "i_out": "measured output current (A)",
    "power": "measured output power (W)",
    "output": "output (or load input) enable, 0/1 (or the command values 'on'/'off')",
    "output_state": "output (or load input) state as read, 0/1, where 'output' is a command",
    "mode": "CV/CC, 1 = constant current",
    "protection": "protection state (see codes/flags)",
    "ovp": "over-voltage protection level (V)",
    "ocp": "over-current protection level (A)",
    "opp": "over-power protection level (W)",
    "polarity_x": "H-bridge relay of the x coil, 1 = reversed",
    "polarity_y": "H-bridge relay of the y coil, 1 = reversed",
    "polarity_z": "H-bridge relay of the z coil, 1 = reversed",
    "temperature": "the DUT's temperature (degrees C)",
    "serial": "serial number",
    "constant": "always reads 'value' (a model number)",
    "none": "no meaning to the rig (kept by the simulator)",
}
DEVICE_KEYS = ("kind", "model", "v_max", "i_max", "bipolar", "baudrate", "write_function",
               "undefined_reads")  # fmt: skip
UNDEFINED_READS = ("exception", "zero")
"""What a read of an unlisted address answers: exception 2, or 0 (``[device] undefined_reads``)."""
REGISTER_KEYS = ("name", "address", "type", "scale", "unit", "access", "role", "value", "codes",
                 "flags", "on", "off", "mirror")  # fmt: skip
TOP_KEYS = ("device", "registers")
DEFAULT_CODES = ("", "OVP", "OCP")
REPEATABLE_ROLES = ("none", "constant")
"""Roles more than one register may have; every other role names one register."""
ADDRESS_MAX = 0xFFFF
"""Highest Modbus register address."""
MAX_REGISTERS = 4096
"""Most registers a map may list (a real device's map lists tens): a larger one is refused."""
MAX_MAP_BYTES = 4 * 1024 * 1024
"""Largest map file (bytes) read at all."""
MAX_NAME_CHARS = 64
"""Longest register, code or flag name (characters)."""
MAX_MODEL_CHARS = 128
"""Longest model name (characters)."""
MAX_SCALE = 1e9
"""Largest scale (counts per unit): a nano-unit a count."""
MAX_CODES = 256
"""Most protection codes a register may list."""
_RANGES = {"uint16": (0, 0xFFFF), "int16": (-0x8000, 0x7FFF),
           "uint32": (0, 0xFFFFFFFF), "int32": (-0x80000000, 0x7FFFFFFF)}  # fmt: skip


class RegisterMapError(ValueError):
    """A register-map file is malformed or missing; the message names the file, line and fix."""


@dataclass(frozen=True)
class Register:
    """One value: its address, encoding and role."""

    name: str
    address: int
    type: str
    access: str
    role: str
    scale: float = 1.0
    value: float | None = None  # role "constant": what it always reads; else power-on value
    codes: tuple[str, ...] = DEFAULT_CODES
    flags: tuple[str, ...] = ()
    on: float = 1.0  # role "output": the value written to switch on
    off: float = 0.0  # and off
    mirror: str | None = None  # the register (by name) this address is a second one of

    @property
    def width(self) -> int:
        """Number of 16-bit registers."""
        return TYPES[self.type]

    def limits(self) -> tuple[float, float]:
        """Lowest and highest physical value the register can hold."""
        if self.type == "float32":
            return (-3.4e38, 3.4e38)
        lo, hi = _RANGES[self.type]
        return (lo / self.scale, hi / self.scale)

    def encode(self, value: float, *, saturate: bool = False) -> list[int]:
        """Physical value to register words. A value that does not fit raises ValueError, or
        with ``saturate`` is held at the nearest end (a simulated instrument's display)."""
        if self.type == "float32":
            return list(struct.unpack(">HH", struct.pack(">f", value)))
        counts = round(value * self.scale)
        lo, hi = _RANGES[self.type]
        if saturate:
            counts = max(lo, min(hi, counts))
        elif not lo <= counts <= hi:
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

    def protection_name(self, raw: int) -> str:
        """A protection register's value as "" (none), "OVP", "OCP", ... or "code N"."""
        if self.flags:
            names = [f for i, f in enumerate(self.flags) if raw & (1 << i)]
            unknown = raw & ~((1 << len(self.flags)) - 1)
            return "+".join(names + ([f"code {unknown}"] if unknown else []))
        if 0 <= raw < len(self.codes):
            return self.codes[raw]
        return f"code {raw}"

    def protection_value(self, name: str) -> int:
        """The register value that reports protection ``name`` ("" = none); the simulator's side
        of :meth:`protection_name`. ValueError for a name the register cannot report."""
        if not name:
            return 0
        if self.flags:
            return 1 << self.flags.index(name)
        return self.codes.index(name)


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
    write_function: int = 6  # 16: the device has no Write Single Register (function 6)
    undefined_reads: str = "exception"  # "zero": an unlisted address reads 0 on the device

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
    if p.is_file():
        return p
    shipped = MAP_DIR / (name_or_path if name_or_path.endswith(".toml") else f"{name_or_path}.toml")
    if shipped.is_file():
        return shipped
    names = ", ".join(sorted(f.stem for f in MAP_DIR.glob("*.toml")))
    raise RegisterMapError(
        f"register map '{name_or_path}' not found; give a path or one of: {names}"
    )


class _Lines:
    """Line numbers of the ``[device]`` keys and of each ``[[registers]]`` entry's keys.

    Indexed once (one pass over the text): finding a register's line is then a lookup and a scan
    of that register's own block, so a map of n registers is checked in time linear in n (the
    scan of every header per register made 30000 registers take minutes, issue 51)."""

    def __init__(self, text: str) -> None:
        self.lines = text.splitlines()
        self.header_lines: list[int] = []  # every header's line (1-based), ascending
        self.starts: dict[str, list[int]] = {}  # header (spaces removed) -> its lines, in order
        for i, line in enumerate(self.lines):
            if m := re.match(r"\s*(\[\[?[^\]]+\]\]?)", line):
                self.header_lines.append(i + 1)
                self.starts.setdefault(m.group(1).replace(" ", ""), []).append(i + 1)

    def _block(self, header: str, index: int) -> tuple[int, int]:
        starts = self.starts.get(header, [])
        if index >= len(starts):
            return (1, len(self.lines))
        start = starts[index]
        after = bisect.bisect_right(self.header_lines, start)
        end = self.header_lines[after] - 1 if after < len(self.header_lines) else len(self.lines)
        return (start, end)

    def top(self, key: str) -> int:
        """Line of a top-level key or table named ``key`` (1 if not found)."""
        for n, line in enumerate(self.lines, 1):
            if re.match(rf"\s*(\[+\s*)?{re.escape(key)}\b", line):
                return n
        return 1

    def of(self, header: str, index: int, key: str | None = None) -> int:
        """Line (1-based) of ``key`` in the ``index``-th block under ``header``, or the header."""
        start, end = self._block(header, index)
        if key is not None:
            pattern = re.compile(rf"\s*{re.escape(key)}\s*=")
            for n in range(start, end + 1):
                if pattern.match(self.lines[n - 1]):
                    return n
        return start


def _nearest(word: str, valid: Any) -> str:
    options = list(valid)
    match = difflib.get_close_matches(word, options, n=1, cutoff=0.0)
    return f"did you mean '{match[0]}'?" if match else f"use one of {', '.join(options)}"


def _check_keys(where: Callable[[str], str], got: dict[str, Any], valid: tuple[str, ...]) -> None:
    for key in got:
        if key not in valid:
            raise RegisterMapError(f"{where(key)}: unknown key '{key}'; {_nearest(key, valid)}")


def _choice(where: str, what: str, value: Any, valid: Any) -> str:
    if not isinstance(value, str) or value not in valid:
        raise RegisterMapError(
            f"{where}: unknown {what} {value!r}; {_nearest(str(value), valid)}"
            f" (valid: {', '.join(valid)})"
        )
    return value


def _names(where: str, value: Any) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise RegisterMapError(f'{where}: must be a list of names, e.g. ["OVP", "OCP"]')
    return tuple(value)


def _finite(
    where: str, what: str, value: Any, fix: str, *, positive: bool = False, high: float = math.inf
) -> float:
    """``value`` as a finite float (above 0 with ``positive``, at most ``high``), else a one-line
    error with ``fix``."""
    try:
        ok = not isinstance(value, bool) and isinstance(value, int | float)
        x = float(value) if ok else math.nan
    except OverflowError:  # an integer beyond any float
        x = math.inf
    shown = repr(value) if len(repr(value)) <= 40 else repr(value)[:37] + "..."
    if not math.isfinite(x) or (positive and x <= 0.0):
        need = "a finite number above 0" if positive else "a finite number"
        raise RegisterMapError(f"{where}: {what} is {shown}; it must be {need}: {fix}")
    if x > high:
        raise RegisterMapError(f"{where}: {what} is {shown}; it must be at most {high:g}: {fix}")
    return x


def _label(where: str, what: str, value: Any, max_chars: int) -> str:
    """A name or model: printable text (no control, bidi or zero-width character), not empty."""
    if not isinstance(value, str) or not value or len(value) > max_chars or not value.isprintable():
        raise RegisterMapError(
            f"{where}: {what} {str(value)[:40]!r} must be printable text of 1 to {max_chars}"
            " characters; rename it"
        )
    return value


def _register(at: Callable[..., str], i: int, r: Any) -> Register:
    """The ``i``-th ``[[registers]]`` table, every value checked; ``at(key)`` names its line."""
    if not isinstance(r, dict):
        raise RegisterMapError(f"{at()}: registers[{i}] must be a table ([[registers]])")
    for key in r:
        if key not in REGISTER_KEYS:
            raise RegisterMapError(
                f"{at(key)}: unknown key '{key}'; {_nearest(key, REGISTER_KEYS)}"
            )
    if "name" not in r or "address" not in r:
        raise RegisterMapError(f"{at()}: registers[{i}] needs a name and an address")
    name = _label(at("name"), "the register name", r["name"], MAX_NAME_CHARS)
    what = f"register '{name}'"
    type_ = _choice(at("type"), "type", r.get("type"), TYPES)
    access = _choice(at("access"), "access", r.get("access", "ro"), ACCESS)
    role = _choice(at("role"), "role", r.get("role", "none"), ROLES)
    address = r["address"]
    last = ADDRESS_MAX - TYPES[type_] + 1  # a 32-bit register takes two addresses
    if isinstance(address, bool) or not isinstance(address, int) or not 0 <= address <= last:
        raise RegisterMapError(
            f"{at('address')}: {what}: address {address!r} is outside the Modbus address space"
            f" (0 to {last:#06x} for a {type_}); give the device's register address"
        )
    scale = _finite(at("scale"), f"{what}: scale", r.get("scale", 1.0),
                    "counts per unit, e.g. 100 for 0.01 A a count", positive=True,
                    high=MAX_SCALE)  # fmt: skip
    if ("codes" in r or "flags" in r) and role != "protection":
        raise RegisterMapError(f"{at('codes' if 'codes' in r else 'flags')}: codes and flags"
                               " belong to a register with role 'protection'")  # fmt: skip
    if ("on" in r or "off" in r) and role != "output":
        raise RegisterMapError(f"{at('on' if 'on' in r else 'off')}: on and off belong to a"
                               " register with role 'output'")  # fmt: skip
    codes, flags = _codes_and_flags(at, r, name, type_)
    numbers = _numbers(
        at, r, Register(name, address, type_, access, role, scale, None, codes, flags)
    )
    mirror = _label(at("mirror"), f"{what}: mirror", r["mirror"], MAX_NAME_CHARS) \
        if "mirror" in r else None  # fmt: skip
    return Register(name, address, type_, access, role, scale, numbers.get("value"), codes, flags,
                    numbers.get("on", 1.0), numbers.get("off", 0.0), mirror)  # fmt: skip


def _check_mirrors(regs: list[Register], p: str, lines: _Lines) -> None:
    """Every ``mirror`` names another register, not itself a mirror, of the same type and scale."""
    by_name = {r.name: r for r in regs}
    for i, reg in enumerate(regs):
        if reg.mirror is None:
            continue
        target = by_name.get(reg.mirror)
        where = f"{p}:{lines.of('[[registers]]', i, 'mirror')}: register '{reg.name}'"
        if target is None or target is reg or target.mirror is not None:
            raise RegisterMapError(f"{where}: mirror '{reg.mirror}' is not another register of"
                                   f" this map; {_nearest(reg.mirror, by_name)}")  # fmt: skip
        if (target.type, target.scale) != (reg.type, reg.scale):
            raise RegisterMapError(f"{where}: mirrors '{target.name}' ({target.type}, scale"
                                   f" {target.scale:g}) with type {reg.type} and scale"
                                   f" {reg.scale:g}; give both the same")  # fmt: skip


def _codes_and_flags(
    at: Callable[..., str], r: dict[str, Any], name: str, type_: str
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """A protection register's codes and flags: names, no more than it can report."""
    what = f"register '{name}'"
    codes = _names(at("codes"), r["codes"]) if "codes" in r else DEFAULT_CODES
    flags = _names(at("flags"), r["flags"]) if "flags" in r else ()
    if len(codes) > MAX_CODES or len(flags) > 16 * TYPES[type_]:
        key = "codes" if len(codes) > MAX_CODES else "flags"
        raise RegisterMapError(
            f"{at(key)}: {what} has more {key} than it can report ({MAX_CODES} codes, or one flag"
            f" a bit of its {16 * TYPES[type_]}); remove the extra ones"
        )
    for key, names in (("codes", codes), ("flags", flags)):
        for code in names:
            if code:
                _label(at(key), f"{what}: the {key[:-1]}", code, MAX_NAME_CHARS)
    return codes, flags


def _numbers(at: Callable[..., str], r: dict[str, Any], reg: Register) -> dict[str, float]:
    """``value``, ``on`` and ``off`` where given: finite, and each fits ``reg``'s type and scale."""
    numbers: dict[str, float] = {}
    what = f"register '{reg.name}'"
    for key in ("value", "on", "off"):
        if r.get(key) is None:
            continue
        numbers[key] = _finite(
            at(key), f"{what}: {key}", r[key], "give the value it reads or takes"
        )
        try:
            reg.encode(numbers[key])
        except (ValueError, OverflowError):
            lo, hi = reg.limits()
            raise RegisterMapError(
                f"{at(key)}: {what}: {key} {r[key]!r} does not fit a {reg.type} of scale"
                f" {reg.scale:g} ({lo:g} to {hi:g}); fix the value, the type or the scale"
            ) from None
    return numbers


def parse_map(text: str, source: str, *, max_registers: int | None = None) -> RegisterMap:
    """Parse and check a map's TOML ``text`` (``source``: the file named in every error).

    Refuses, in one line naming the file, line and register and the fix: an unknown key, kind,
    type, access or role; a register name or model that is not printable text; an address outside
    0-65535 (a 32-bit register's second word included); a scale, ``v_max`` or ``i_max`` that is
    not a finite number above 0; a ``value``, ``on`` or ``off`` that is not finite or does not fit
    its register; overlapping registers; two registers of one name or of one role (``none`` and
    ``constant`` may repeat); more than ``max_registers`` registers (default
    :data:`MAX_REGISTERS`). Time linear in the number of registers."""
    cap = MAX_REGISTERS if max_registers is None else max_registers
    p = source
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RegisterMapError(f"{p}: not valid TOML ({exc})") from None
    dev = raw.get("device", {})
    registers = raw.get("registers", [])
    if isinstance(registers, list) and len(registers) > cap:
        raise RegisterMapError(
            f"{p}: {len(registers)} registers, more than the {cap} a map may have"
            " (MAX_REGISTERS); list only the registers the rig uses"
        )
    lines = _Lines(text)
    _check_keys(lambda key: f"{p}:{lines.top(key)}", raw, TOP_KEYS)
    if not isinstance(dev, dict):
        raise RegisterMapError(f"{p}:{lines.top('device')}: 'device' must be a table ([device])")
    if not isinstance(registers, list):
        raise RegisterMapError(
            f"{p}:{lines.top('registers')}: 'registers' must be tables ([[registers]])"
        )
    _check_keys(lambda key: f"{p}:{lines.of('[device]', 0, key)}", dev, DEVICE_KEYS)
    regs = _registers(registers, p, lines)
    _check_mirrors(regs, p, lines)
    spans = sorted((r.address, r.address + r.width, r.name) for r in regs)
    for (_, a1, n0), (b0, _, n1) in itertools.pairwise(spans):
        if b0 < a1:
            raise RegisterMapError(
                f"{p}: registers '{n0}' and '{n1}' overlap at {b0:#06x}; fix an address or a type"
            )
    return _device(dev, p, lines, tuple(regs))


def _registers(registers: list[Any], p: str, lines: _Lines) -> list[Register]:
    """Every ``[[registers]]`` table checked; no name twice, no role but ``none`` and
    ``constant`` twice."""
    regs: list[Register] = []
    by_name: dict[str, int] = {}
    by_role: dict[str, str] = {}
    for i, r in enumerate(registers):

        def at(key: str | None = None, i: int = i) -> str:
            return f"{p}:{lines.of('[[registers]]', i, key)}"

        reg = _register(at, i, r)
        if reg.name in by_name:
            raise RegisterMapError(f"{at('name')}: a second register named '{reg.name}' (the"
                                   f" first is registers[{by_name[reg.name]}]); rename one")  # fmt: skip
        by_name[reg.name] = i
        if reg.role not in REPEATABLE_ROLES:
            if reg.role in by_role:
                raise RegisterMapError(
                    f"{at('role')}: register '{reg.name}' has the role '{reg.role}' of register"
                    f" '{by_role[reg.role]}' already; give one of them role 'none'"
                )
            by_role[reg.role] = reg.name
        regs.append(reg)
    return regs


def _device(dev: dict[str, Any], p: str, lines: _Lines, regs: tuple[Register, ...]) -> RegisterMap:
    """The ``[device]`` table checked, with the map's registers: the map."""
    kind = _choice(f"{p}:{lines.of('[device]', 0, 'kind')}", "kind", dev.get("kind"), KINDS)
    model = _label(f"{p}:{lines.of('[device]', 0, 'model')}", "the model",
                   dev.get("model", Path(p).stem), MAX_MODEL_CHARS)  # fmt: skip
    limits: dict[str, float] = {}
    for key, unit in (("v_max", "V"), ("i_max", "A")):
        where = f"{p}:{lines.of('[device]', 0, key)}"
        if key in dev:
            limits[key] = _finite(where, key, dev[key],
                                  f"the device's full-scale output ({unit})", positive=True)  # fmt: skip
        elif kind in ("supply", "eload"):
            raise RegisterMapError(
                f"{where}: a {kind} map needs {key} (its full-scale output, {unit}); add it"
            )
    bipolar = dev.get("bipolar", False)
    if not isinstance(bipolar, bool):
        raise RegisterMapError(
            f"{p}:{lines.of('[device]', 0, 'bipolar')}: bipolar must be true or false"
        )
    baudrate = dev.get("baudrate")
    if baudrate is not None and (
        isinstance(baudrate, bool)
        or not isinstance(baudrate, int)
        or not 50 <= baudrate <= 4_000_000
    ):
        raise RegisterMapError(f"{p}:{lines.of('[device]', 0, 'baudrate')}: baudrate must be a"
                               " whole number of 50 to 4000000, e.g. 9600")  # fmt: skip
    write_function = dev.get("write_function", 6)
    if write_function not in (6, 16) or isinstance(write_function, bool):
        raise RegisterMapError(
            f"{p}:{lines.of('[device]', 0, 'write_function')}: write_function must be 6 or 16"
        )
    undefined = _choice(f"{p}:{lines.of('[device]', 0, 'undefined_reads')}", "undefined_reads",
                        dev.get("undefined_reads", "exception"), UNDEFINED_READS)  # fmt: skip
    return RegisterMap(kind, model, regs, limits.get("v_max", 0.0), limits.get("i_max", 0.0),
                       bipolar, str(p), baudrate, int(write_function), undefined)  # fmt: skip


@lru_cache(maxsize=64)
def _load(path: str, mtime_ns: int) -> RegisterMap:
    p = Path(path)
    size = p.stat().st_size
    if size > MAX_MAP_BYTES:
        raise RegisterMapError(
            f"{p}: {size} bytes, more than the {MAX_MAP_BYTES} a register map may have"
            " (MAX_MAP_BYTES); list only the registers the rig uses"
        )
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise RegisterMapError(f"{p}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    return parse_map(text, str(p))


def load_map(name_or_path: str) -> RegisterMap:
    """Parse and check a register map (a path, or the name of a shipped map)."""
    p = find_map(name_or_path)
    return _load(str(p), p.stat().st_mtime_ns)


def shipped_maps() -> list[RegisterMap]:
    """Every map in this folder (sorted by name)."""
    return [load_map(str(f)) for f in sorted(MAP_DIR.glob("*.toml"))]
