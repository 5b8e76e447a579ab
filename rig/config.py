"""Rig configuration (TOML): devices, ports, addresses, cage limits and channel names.

    [cage]
    axes = { x = "coil_x", y = "coil_y", z = "coil_z" }   # supply per coil axis
    polarity = "polarity"            # relay board; omit when every coil supply is bipolar
    reference = "reference"          # magnetometer for trim and characterization
    calibration = "cage.json"        # cage model file (relative to this file); optional
    max_current_a = [2.0, 2.0, 2.0]
    max_field_ut = 150.0
    max_slew_a_per_s = 4.0
    compliance_v = 20.0

    [devices.coil_x]
    kind = "riden-rd60xx"            # see drivers/registry.py (rig devices scan)
    protocol = "modbus-tcp"          # or modbus-rtu, serial, i2c
    host = "127.0.0.1"
    port = 5020
    device_id = 1

Every key is declared once, as a :class:`drivers.config_keys.Param` (type, unit, accepted values,
default, help): a device's in :mod:`drivers.registry`, the ``[cage]`` table's in
:data:`CAGE_KEYS`, the ``[lab]`` table's in :data:`LAB_KEYS`. The loader fills in the
declared defaults and refuses any other key with the file, the line and the nearest valid key.
``python -m rig.config --doc`` prints the key tables of ``docs/devices.md`` from the same
declarations (``--doc --write`` updates the file).

Every error names the file and the key and says what to write instead. Every string, keys
included, follows the rule of :mod:`rig.text` (it is copied into each run folder and the lab
index): no control characters but tab, and names, serials and other labels at most
``MAX_TEXT_CHARS`` characters (paths, host names and URLs: no limit of their own). The values each device
key accepts (a TCP port 1-65535, a Modbus RTU address 1-247, a standard baud rate, ...) are stated
once, in the key's :class:`drivers.registry.Param`.
"""

from __future__ import annotations

import argparse
import copy
import difflib
import math
import re
import sys
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.config_keys import LIST, NUMBER, TABLE, TEXT, Param
from drivers.registry import KINDS, RECORD_KEYS, TRANSPORTS, DeviceKind, Role, kinds_with_role
from rig.errors import UserInputError
from rig.text import shown, text_problem

DEVICE_KINDS: dict[str, tuple[str, ...]] = {name: k.transports for name, k in KINDS.items()}
"""Kind name -> transports it accepts (derived from :mod:`drivers.registry`)."""

CAGE_KEYS: tuple[Param, ...] = (
    Param("axes", TABLE, True, help='the supply of each coil axis: { x = "...", y = "...",'
          ' z = "..." }'),
    Param("polarity", TEXT, help="the polarity relay board; omit when every coil supply is bipolar"),
    Param("reference", TEXT, help="the magnetometer for trim and characterization"),
    Param("calibration", TEXT, help="the cage model file (relative to the rig configuration),"
          " written by rig cage characterize"),
    Param("calibration_valid_days", NUMBER, False, 90.0, "how long a cage characterization holds:"
          " rig check warns about an older one", above=0.0,
          fix="write the validity, e.g. calibration_valid_days = 90", unit="days"),
    Param("ambient", TEXT, help="a magnetometer outside the coils, recorded in every run: the"
          " lab field's changes"),
    Param("scalar", TEXT, help="a total-field (scalar) magnetometer at the cage centre: the coil"
          " constants and axis angles without a certificate (the coil_scalar step)"),
    Param("ambient_gradient_nt_per_m", NUMBER, False, 15.0, "1-sigma of each component of the"
          " lab field's gradient at the DUT: the uncertainty budget's term for the reference"
          " sitting elsewhere", low=0.0,
          fix="write the gradient's uncertainty, e.g. ambient_gradient_nt_per_m = 15",
          unit="nT/m"),
    Param("trim", TABLE, help='the supplies of trim windings, one per coil axis (the ambient'
          ' servo\'s fine stage): { x = "...", y = "...", z = "..." }'),
    Param("trim_ut_per_a", LIST, help="each trim winding's field per ampere along its coil's"
          " axis [x, y, z]", unit="uT/A"),
    Param("max_current_a", LIST, True, help="coil current limit per axis [x, y, z]", unit="A"),
    Param("max_field_ut", NUMBER, True, help="largest field magnitude a procedure may ask for",
          above=0.0, fix="write the cage's field limit, e.g. max_field_ut = 150.0", unit="uT"),
    Param("max_ambient_ut", NUMBER, False, 66.0, "the largest lab field at the cage before a"
          " characterization measures it (a handheld reading with a margin; 66 uT holds anywhere"
          " on Earth): the field limit counts it until then", above=0.0,
          fix="write the lab field's bound, e.g. max_ambient_ut = 66.0", unit="uT"),
    Param("max_slew_a_per_s", NUMBER, True, help="coil current slew limit", above=0.0,
          fix="write the slew limit, e.g. max_slew_a_per_s = 4.0", unit="A/s"),
    Param("coil_tau_s", NUMBER, help="the shortest coil's L/R time constant: ramps are then"
          " planned so that the coil current itself, not only its set-points, never changes"
          " faster than max_slew_a_per_s (each set-point step into the coil peaks at"
          " step / (tau (1 - exp(-step_s / tau))) A/s)", above=0.0,
          fix="write the L/R of the coils, e.g. coil_tau_s = 0.025", unit="s"),
    Param("compliance_v", NUMBER, False, 20.0, "the coil supplies' voltage set-point", above=0.0,
          fix="write the voltage set-point, e.g. compliance_v = 20.0", unit="V"),
    Param("step_s", NUMBER, False, 0.05, "interval between set-points of a ramp", above=0.0,
          fix="write the interval, e.g. step_s = 0.05", unit="s"),
    Param("nominal_k_ut_per_a", LIST, help="nameplate coil constants (3x3, field per current)"
          " until the cage is characterized", unit="uT/A"),
)  # fmt: skip
"""The keys of the ``[cage]`` table."""

LAB_KEYS: tuple[Param, ...] = (
    Param("url", TEXT, help="the lab index: postgresql://USER@HOST:PORT/DATABASE, never a password"
          " (docs/lab.md)", nonempty=True),
    Param("rig", TEXT, help="this rig's name in the lab index (default: the host name)"),
)  # fmt: skip
"""The keys of the ``[lab]`` table (the URL's own rules, no password in it, are checked where it is
used: :func:`rig.lab.url.config_url`)."""

TABLES: dict[str, tuple[Param, ...] | None] = {"devices": None, "cage": CAGE_KEYS, "lab": LAB_KEYS}
"""The top-level tables of a rig configuration and their keys (``devices``: one table per
device, its keys from :mod:`drivers.registry`)."""


@dataclass(frozen=True)
class DeviceConfig:
    """One device: its kind, transport and the transport's and kind's parameters (the declared
    defaults filled in by :func:`load_rig_config`)."""

    name: str
    kind: str
    protocol: str
    params: dict[str, Any]

    def get(self, key: str, default: Any = None) -> Any:
        """A parameter; a declared key with a default is always there (no ``default`` needed),
        ``default`` is for optional keys without one (e.g. ``max_current_a``)."""
        return self.params.get(key, default)

    @property
    def where(self) -> str:
        """Where the device is, for people: ``host:port id N``, ``/dev/ttyUSB0 id N``, a serial
        port, or ``i2c bus N address 0xNN``."""
        p = self.params
        if self.protocol == "i2c":
            address = p.get("address")
            at = f" address {address:#04x}" if isinstance(address, int) else ""
            return f"i2c bus {p.get('bus')}{at}"
        place = f"{p['host']}:{p.get('port')}" if "host" in p else str(p.get("path", ""))
        if self.protocol.startswith("modbus") and "device_id" in p:
            place += f" id {p['device_id']}"
        return place


def coil_step_a(max_slew_a_per_s: float, dt_s: float, coil_tau_s: float | None) -> float:
    """The largest set-point change (A) ``dt_s`` after the last one that keeps a coil current's
    slope within ``max_slew_a_per_s``: ``slew * dt`` for an ideal coil; into a coil of L/R
    ``tau`` still moving towards the last set-point, ``slew * tau * (1 - exp(-dt / tau))`` (a
    steady staircase's peak slope, step / (tau (1 - exp(-dt / tau))), at the limit)."""
    if coil_tau_s is None:
        return max_slew_a_per_s * dt_s
    return max_slew_a_per_s * coil_tau_s * -math.expm1(-dt_s / coil_tau_s)


@dataclass(frozen=True)
class CageConfig:
    """Which devices make the cage, and its limits (units as in :data:`CAGE_KEYS`)."""

    axes: tuple[str, str, str]
    polarity: str | None
    reference: str | None
    calibration: Path | None
    max_current_a: tuple[float, float, float]
    max_field_ut: float
    max_slew_a_per_s: float
    compliance_v: float
    step_s: float = 0.05
    nominal_k_ut_per_a: tuple[tuple[float, ...], ...] | None = None
    calibration_valid_days: float = 90.0
    ambient: str | None = None
    scalar: str | None = None
    ambient_gradient_nt_per_m: float = 15.0
    trim: tuple[str, str, str] | None = None
    trim_ut_per_a: tuple[float, float, float] | None = None
    max_ambient_ut: float = 66.0
    coil_tau_s: float | None = None

    @property
    def ramp_slew_a_per_s(self) -> float:
        """The average slew (A/s) ramps are planned at: ``max_slew_a_per_s``, or with
        ``coil_tau_s`` the rate whose set-point steps (one per ``step_s``) into a first-order
        coil of that L/R peak at exactly ``max_slew_a_per_s``:
        ``max_slew * tau (1 - exp(-step_s / tau)) / step_s``."""
        return coil_step_a(self.max_slew_a_per_s, self.step_s, self.coil_tau_s) / self.step_s


@dataclass(frozen=True)
class RigConfig:
    """The whole rig configuration."""

    path: Path
    devices: dict[str, DeviceConfig]
    cage: CageConfig | None = None
    raw: dict[str, Any] = field(default_factory=dict)


PATH_KEYS = frozenset({"path", "regmap", "calibration", "host", "url"})
"""Keys whose strings are paths, host names or URLs: no length limit of their own."""


def _refuse_bad_text(path: Path, value: Any, where: str, key: str = "") -> None:
    """A one-line :class:`UserInputError` naming the key of the first string anywhere in the
    configuration (keys included) that breaks the rule of :mod:`rig.text`."""
    if isinstance(value, str):
        problem = text_problem(value, label=key not in PATH_KEYS, allowed="\t")
        if problem is not None:
            raise _err(path, where, f"{shown(value)} {problem}")
    elif isinstance(value, dict):
        for k, v in value.items():
            k = str(k)
            if (problem := text_problem(k)) is not None:
                raise _err(path, where or "the top level", f"the key {shown(k)} {problem}")
            if not where:
                inner = f"[{k}]"
            elif where.startswith("[") and where.endswith("]") and isinstance(v, dict):
                inner = f"{where[:-1]}.{k}]"  # [devices.coil_x], as the file writes it
            else:
                inner = f"{where}.{k}"
            _refuse_bad_text(path, v, inner, k)
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _refuse_bad_text(path, v, f"{where}[{i}]", key)


def _err(path: Path, where: str, msg: str) -> UserInputError:
    return UserInputError(f"{path}: {where}: {msg}")


# --- where a key is written (tomllib gives no line numbers) -------------------------------------

_HEADER = re.compile(r"^\s*\[\[?\s*([^\[\]#]+?)\s*\]\]?\s*(#.*)?$")
_KEY = re.compile(
    r"""^\s*((?:"[^"]*"|'[^']*'|[A-Za-z0-9_\-]+)(?:\s*\.\s*(?:"[^"]*"|'[^']*'|[A-Za-z0-9_\-]+))*)\s*="""
)
_PART = re.compile(r""""([^"]*)"|'([^']*)'|([A-Za-z0-9_\-]+)""")


def _parts(dotted: str) -> tuple[str, ...]:
    """``devices."coil x".port`` -> ("devices", "coil x", "port")."""
    return tuple(next(g for g in m.groups() if g is not None) for m in _PART.finditer(dotted))


def _in_inline_table(rest: str, key: str) -> bool:
    """Does the inline table ``rest`` (the text after ``name =``) write ``key``?"""
    return re.search(r"[{,]\s*(?:" + re.escape(key) + r"|\"" + re.escape(key) + r"\")\s*[=.]",
                     rest) is not None  # fmt: skip


def line_of(text: str, path: tuple[str, ...]) -> int | None:
    """The line (1-based) where the table or key ``path`` (e.g. ("devices", "dut", "port")) is
    written: its header, its ``key =`` line (dotted keys too) or the line of the inline table that
    holds it; else the first line inside it; None when not found."""
    table: tuple[str, ...] = ()
    inside: int | None = None
    for n, line in enumerate(text.splitlines(), 1):
        if m := _HEADER.match(line):
            table = _parts(m.group(1))
            found = table
        elif m := _KEY.match(line):
            found = table + _parts(m.group(1))
            rest = line[m.end() :]
            n_found = len(found)
            inline = found == path[:n_found] and n_found < len(path) and "{" in rest
            if inline and _in_inline_table(rest, path[n_found]):
                return n
        else:
            continue
        if found == path:
            return n
        if inside is None and found[: len(path)] == path:
            inside = n
    return inside


def _nearest(key: str, valid: Iterable[str]) -> str:
    """``"; did you mean 'stuck_after'?"`` (difflib), else the valid keys."""
    options = sorted(set(valid))
    match = difflib.get_close_matches(key, options, n=1, cutoff=0.6)
    if match:
        return f"; did you mean '{match[0]}'?"
    return f"; the keys here: {', '.join(options)}" if options else ""


@dataclass(frozen=True)
class _Source:
    """The file being loaded: its path and text, to name the line of a key in an error."""

    path: Path
    text: str
    lenient: bool = False
    """Unknown keys and tables are passed over, not refused (``rig safe``)."""

    def unknown(self, table: tuple[str, ...], key: str, valid: Iterable[str],
                note: str = "") -> UserInputError:  # fmt: skip
        """``rig.toml:7: [devices.dut].stuk_after: unknown key; did you mean 'stuck_after'?``"""
        line = line_of(self.text, (*table, key))
        at = f"{self.path}:{line}" if line is not None else f"{self.path}"
        where = f"[{'.'.join(table)}].{key}" if table else f"[{key}]"
        hint = note or _nearest(key, valid)
        return UserInputError(f"{at}: {where}: unknown {'key' if table else 'table'}{hint}")


# --- devices ------------------------------------------------------------------------------------


def device_keys(kind: DeviceKind, protocol: str) -> dict[str, Param]:
    """Every key a device of ``kind`` over ``protocol`` accepts, by name (``kind`` and
    ``protocol`` themselves aside)."""
    return {p.name: p for p in kind.param_specs(protocol)}


def _elsewhere(key: str, kind: DeviceKind, protocol: str) -> str:
    """A note when ``key`` is another transport's or kind's: where it belongs."""
    transports = [t for t, ps in TRANSPORTS.items() if any(p.name == key for p in ps)]
    kinds = [k.name for k in KINDS.values() if any(p.name == key for p in k.params)]
    if not transports and not kinds:
        return ""
    owners = ", ".join([*(f"{t} devices" for t in transports), *kinds])
    valid = ", ".join(sorted({*device_keys(kind, protocol), "kind", "protocol"}))
    return f": it is a key of {owners}, not of {kind.name} over {protocol} (its keys: {valid})"


def _kind_and_protocol(path: Path, where: str, spec: dict[str, Any]) -> tuple[DeviceKind, str]:
    kind = spec.get("kind")
    if not isinstance(kind, str) or kind not in KINDS:
        raise _err(path, f"{where}.kind", f"{kind!r} is not one of {', '.join(KINDS)}")
    entry = KINDS[kind]
    protocol = spec.get("protocol")
    if not isinstance(protocol, str) or protocol not in entry.transports:
        raise _err(
            path,
            f"{where}.protocol",
            f"{protocol!r} does not suit {kind}; use {' or '.join(entry.transports)}",
        )
    return entry, protocol


def _device(src: _Source, name: str, spec: Any) -> DeviceConfig:
    """One ``[devices.NAME]`` table checked against its kind's declared keys, defaults filled in."""
    path, where = src.path, f"[devices.{name}]"
    if not isinstance(spec, dict):
        raise _err(path, where, "must be a table")
    entry, protocol = _kind_and_protocol(path, where, spec)
    keys = device_keys(entry, protocol)
    if src.lenient:
        spec = {k: v for k, v in spec.items() if k in keys or k in ("kind", "protocol")}
    for key in spec:
        if key not in keys and key not in ("kind", "protocol"):
            note = _elsewhere(key, entry, protocol)
            raise src.unknown(("devices", name), key, [*keys, "kind", "protocol"], note)
    for param in TRANSPORTS[protocol]:
        if param.required and param.name not in spec:
            raise _err(path, where, f"needs '{param.name}' for {protocol} ({param.help})")
    for param in entry.params:
        if param.required and param.name not in spec:
            raise _err(path, where, f"needs '{param.name}' ({param.help})")
    for key, value in spec.items():
        if key in keys and (problem := keys[key].problem(value)) is not None:
            raise _err(path, f"{where}.{key}", problem)
    params = entry.defaults(protocol) | {
        k: v for k, v in spec.items() if k not in ("kind", "protocol")
    }
    return DeviceConfig(name, entry.name, protocol, params)


def _devices(src: _Source, table: Any) -> dict[str, DeviceConfig]:
    if not isinstance(table, dict):
        raise _err(src.path, "[devices]", "must be a table of [devices.NAME] tables")
    return {name: _device(src, name, spec) for name, spec in table.items()}


def _table(src: _Source, name: str, raw: Any, keys: tuple[Param, ...]) -> dict[str, Any]:
    """A ``[name]`` table checked against its declared ``keys``: unknown keys refused, the type,
    range and presence of each checked, defaults filled in."""
    if not isinstance(raw, dict):
        raise _err(src.path, f"[{name}]", "must be a table")
    declared = {p.name: p for p in keys}
    if src.lenient:
        raw = {k: v for k, v in raw.items() if k in declared}
    for key in raw:
        if key not in declared:
            raise src.unknown((name,), key, declared)
    for p in keys:
        if p.required and p.name not in raw:
            raise _err(src.path, f"[{name}]", f"needs '{p.name}' ({p.help})")
        if p.name in raw and (problem := p.problem(raw[p.name])) is not None:
            raise _err(src.path, f"[{name}].{p.name}", problem)
    defaults: dict[str, Any] = {p.name: copy.copy(p.default) for p in keys if p.default is not None}
    return defaults | dict(raw)


def load_rig_config(path: str | Path, *, check_text: bool = True) -> RigConfig:
    """Parse and validate a rig configuration file. ``check_text=False`` skips the rule of
    :mod:`rig.text` and passes over unknown keys and tables (for ``rig safe``: an emergency stop
    is not refused over a device's serial or a stray key)."""
    path = Path(path)
    if check_text and (problem := text_problem(str(path), label=False)) is not None:
        raise UserInputError(f"{shown(str(path), 80)}: the file's path {problem} (rename it)")
    try:
        text = path.read_text(encoding="utf-8")
        raw = tomllib.loads(text)
    except FileNotFoundError:
        raise UserInputError(
            f"{path}: no such rig configuration; check the path (rig sim --rig-config writes one)"
        ) from None
    except tomllib.TOMLDecodeError as exc:
        raise UserInputError(f"{path}: not valid TOML ({exc}); fix the syntax") from None
    if check_text:
        _refuse_bad_text(path, raw, "")
    src = _Source(path, text, lenient=not check_text)
    for name in list(raw) if not check_text else []:
        if name not in TABLES:
            del raw[name]
    for name in raw:
        if name not in TABLES:
            raise src.unknown((), name, TABLES)
    devices = _devices(src, raw.get("devices", {}))
    if "lab" in raw:
        _table(src, "lab", raw["lab"], LAB_KEYS)
    cage = (
        _cage(path, _table(src, "cage", raw["cage"], CAGE_KEYS), devices) if "cage" in raw else None
    )
    return RigConfig(path, devices, cage, raw)


# --- the cage -----------------------------------------------------------------------------------


def _numbers(path: Path, where: str, value: Any, n: int) -> tuple[float, ...]:
    if (
        not isinstance(value, list)
        or len(value) != n
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        or not all(math.isfinite(v) for v in value)
    ):
        raise _err(path, where, f"must be a list of {n} finite numbers")
    return tuple(float(v) for v in value)


def _device_with_role(path: Path, key: str, name: Any, devices: dict[str, DeviceConfig],
                      role: Role, what: str) -> None:  # fmt: skip
    """Refuse a ``[cage]`` entry that does not name a device of a kind that plays ``role``."""
    kinds = kinds_with_role(role)
    if not isinstance(name, str) or name not in devices or devices[name].kind not in kinds:
        raise _err(path, f"[cage].{key}",
                   f"'{name}' is not {what} in [devices] (kinds: {', '.join(kinds)})")  # fmt: skip


def _axes(
    path: Path, axes: Any, devices: dict[str, DeviceConfig], key: str = "axes"
) -> tuple[str, str, str]:
    if not isinstance(axes, dict) or set(axes) != {"x", "y", "z"}:
        raise _err(
            path,
            f"[cage].{key}",
            f'must name a supply for x, y and z: {key} = {{ x = "...", y = "...", z = "..." }}',
        )
    for ax, name in axes.items():
        _device_with_role(path, f"{key}.{ax}", name, devices, "supply", "a supply")
    return axes["x"], axes["y"], axes["z"]


def _nominal(path: Path, nominal: Any) -> tuple[tuple[float, ...], ...] | None:
    if nominal is None:
        return None
    if not isinstance(nominal, list) or len(nominal) != 3:
        raise _err(path, "[cage].nominal_k_ut_per_a", "must be a 3x3 list of lists (uT/A)")
    k = tuple(_numbers(path, "[cage].nominal_k_ut_per_a", row, 3) for row in nominal)
    _invertible(path, k)
    return k


MAX_K_CONDITION = 1e6
"""Largest condition number of the nominal coil matrix: beyond it the currents for a field are
dominated by rounding (a singular matrix made ``rig check`` an internal error, issue 51)."""


def _invertible(path: Path, k: tuple[tuple[float, ...], ...]) -> None:
    """Refuse a nominal coil matrix (uT/A) the cage model cannot invert for the currents of a
    field: singular, or with a condition number beyond :data:`MAX_K_CONDITION`."""
    import numpy as np

    with np.errstate(all="ignore"):
        cond = float(np.linalg.cond(np.array(k, float)))
    if not math.isfinite(cond) or cond > MAX_K_CONDITION:
        what = "is singular" if not math.isfinite(cond) else f"has condition number {cond:.3g}"
        raise _err(path, "[cage].nominal_k_ut_per_a",
                   f"{what} (at most {MAX_K_CONDITION:g}), so no currents give every field: write"
                   " each field axis's uT per A of each coil, e.g. [[40, 0, 0], [0, 40, 0],"
                   " [0, 0, 40]]")  # fmt: skip


def _cage(path: Path, c: dict[str, Any], devices: dict[str, DeviceConfig]) -> CageConfig:
    """The ``[cage]`` table (keys, types and defaults already checked by :func:`_table`): the
    devices it names and the shapes of its lists."""
    axes = _axes(path, c["axes"], devices)
    polarity, reference = c.get("polarity"), c.get("reference")
    if polarity is not None:
        _device_with_role(path, "polarity", polarity, devices, "relay", "a relay device")
    if reference is not None:
        _device_with_role(path, "reference", reference, devices, "magnetometer", "a magnetometer")
    ambient = c.get("ambient")
    if ambient is not None:
        _device_with_role(path, "ambient", ambient, devices, "magnetometer", "a magnetometer")
    scalar = c.get("scalar")
    if scalar is not None:
        _device_with_role(path, "scalar", scalar, devices, "scalar", "a scalar magnetometer")
    calibration = c.get("calibration")
    max_current = _numbers(path, "[cage].max_current_a", c["max_current_a"], 3)
    return CageConfig(
        axes=axes,
        polarity=polarity,
        reference=reference,
        calibration=(path.parent / calibration) if calibration else None,
        max_current_a=(max_current[0], max_current[1], max_current[2]),
        max_field_ut=float(c["max_field_ut"]),
        max_slew_a_per_s=float(c["max_slew_a_per_s"]),
        compliance_v=float(c["compliance_v"]),
        step_s=float(c["step_s"]),
        nominal_k_ut_per_a=_nominal(path, c.get("nominal_k_ut_per_a")),
        calibration_valid_days=float(c["calibration_valid_days"]),
        ambient=ambient,
        scalar=scalar,
        ambient_gradient_nt_per_m=float(c["ambient_gradient_nt_per_m"]),
        max_ambient_ut=float(c["max_ambient_ut"]),
        coil_tau_s=None if c.get("coil_tau_s") is None else float(c["coil_tau_s"]),
        **_trim(path, c, devices),
    )


def _trim(path: Path, c: dict[str, Any], devices: dict[str, DeviceConfig]) -> dict[str, Any]:
    """``[cage] trim`` (a supply per axis) and ``trim_ut_per_a`` (three numbers), both or none."""
    if c.get("trim") is None and c.get("trim_ut_per_a") is None:
        return {}
    if c.get("trim") is None or c.get("trim_ut_per_a") is None:
        raise _err(path, "[cage].trim", "needs trim_ut_per_a beside it (and the other way round):"
                   " the trim windings' supplies and their field per ampere")  # fmt: skip
    trim = _axes(path, c["trim"], devices, "trim")
    per_a = _numbers(path, "[cage].trim_ut_per_a", c["trim_ut_per_a"], 3)
    if any(v <= 0 for v in per_a):
        raise _err(path, "[cage].trim_ut_per_a", "must be three positive numbers (uT/A)")
    return {"trim": trim, "trim_ut_per_a": (per_a[0], per_a[1], per_a[2])}


# --- the key tables of docs/devices.md, from the declarations ------------------------------------

DOC_BEGIN = "<!-- BEGIN keys: generated by `python -m rig.config --doc --write`; do not edit -->"
DOC_END = "<!-- END keys -->"
DOC_FILE = Path("docs") / "devices.md"  # in the source checkout, where --write is run
_COLUMNS = "| key | type | unit | accepted | default | meaning |"


def _shown(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, str):
        return f'`"{value}"`'
    return f"`{value}`"


def _row(p: Param, *first: str, label: str = "") -> str:
    """One table row: the key (bold when required), type, unit, accepted values, default, help."""
    key = label or f"`{p.name}`"
    key = f"**{key}**" if p.required else key
    accepted = p.accepted
    if len(p.choices) > 6:  # the standard baud rates
        accepted = f"{p.why or 'one of'}: {p.choices[0]} ... {p.choices[-1]}"
    cells = [*first, key, p.wanted, p.unit or "-", accepted or "-", _shown(p.default),
             (p.help + (f" ({p.why})" if p.why and p.why not in p.help else "")).replace("|", "/")]  # fmt: skip
    return "| " + " | ".join(cells) + " |"


def _kind_rows() -> list[str]:
    """One row per distinct kind key (its own, or its version of a transport key, labelled with
    the transports) with the kinds that accept it."""
    rows: list[tuple[str, Param, list[str]]] = []
    for kind in KINDS.values():
        own = [(f"`{p.name}`", p) for p in kind.params]
        for p in kind.transport_keys.values():
            over = [t for t in kind.transports if p.name in {q.name for q in TRANSPORTS[t]}]
            own.append((f"`{p.name}` ({', '.join(over)})", p))
        for label, p in own:
            row = next((r for r in rows if r[:2] == (label, p)), None)  # Params hold lists
            if row is None:
                rows.append(row := (label, p, []))
            row[2].append(f"`{kind.name}`")
    return [_row(p, ", ".join(kinds), label=label) for label, p, kinds in rows]


def keys_doc() -> str:
    """The key tables of ``docs/devices.md`` (Markdown), from the declarations."""
    out = [DOC_BEGIN, "", "Transport keys (required in bold):", "",
           "| transport " + _COLUMNS, "|---" * 7 + "|"]  # fmt: skip
    out += [_row(p, t) for t, params in TRANSPORTS.items() for p in params]
    out += ["", "Each kind's own keys, and its own version of a transport key:", "",
            "| kinds " + _COLUMNS, "|---" * 7 + "|", *_kind_rows()]  # fmt: skip
    for title, params in (("Keys every device accepts (records for the lab index, docs/lab.md):",
                           RECORD_KEYS), ("The `[cage]` table:", CAGE_KEYS),
                          ("The `[lab]` table (docs/lab.md):", LAB_KEYS)):  # fmt: skip
        out += ["", title, "", _COLUMNS, "|---" * 6 + "|", *(_row(p) for p in params)]
    return "\n".join([*out, "", DOC_END])


def with_keys_doc(text: str) -> str:
    """``text`` (docs/devices.md) with its generated block replaced by :func:`keys_doc`."""
    begin, end = text.find(DOC_BEGIN), text.find(DOC_END)
    if begin < 0 or end < begin:
        raise ValueError(f"no generated block ({DOC_BEGIN} ... {DOC_END}) in the text")
    return text[:begin] + keys_doc() + text[end + len(DOC_END) :]


def main(argv: list[str] | None = None) -> int:
    """``python -m rig.config --doc [--write]``: print the key tables, or rewrite them in place in
    docs/devices.md."""
    parser = argparse.ArgumentParser(prog="python -m rig.config", description=main.__doc__)
    parser.add_argument("--doc", action="store_true", required=True,
                        help="the key tables of docs/devices.md, from the declarations")  # fmt: skip
    parser.add_argument("--write", action="store_true", help=f"update {DOC_FILE} in place")
    args = parser.parse_args(argv)
    if args.write:
        DOC_FILE.write_text(with_keys_doc(DOC_FILE.read_text(encoding="utf-8")), encoding="utf-8")
        print(f"wrote {DOC_FILE}")
    else:
        print(keys_doc())
    return 0


if __name__ == "__main__":
    sys.exit(main())
