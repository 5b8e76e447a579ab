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

Every error names the file and the key and says what to write instead. Every string, keys
included, follows the rule of :mod:`rig.text` (it is copied into each run folder and the lab
index): no control characters but tab, and names, serials and other labels at most
``MAX_TEXT_CHARS`` characters (paths, host names and URLs: no limit of their own). The values each device
key accepts (a TCP port 1-65535, a Modbus RTU address 1-247, a standard baud rate, ...) are stated
once, in the key's :class:`drivers.registry.Param`.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.registry import KINDS, TRANSPORTS, all_params, kinds_with_role
from rig.errors import UserInputError
from rig.text import shown, text_problem

DEVICE_KINDS: dict[str, tuple[str, ...]] = {name: k.transports for name, k in KINDS.items()}
"""Kind name -> transports it accepts (derived from :mod:`drivers.registry`)."""
PARAM_TYPES: dict[str, tuple[type, ...]] = {name: p.types for name, p in all_params().items()}
"""Types of the device parameters the drivers read (others are passed through)."""
REQUIRED: dict[str, tuple[str, ...]] = {
    protocol: tuple(p.name for p in params if p.required) for protocol, params in TRANSPORTS.items()
}
"""Parameters each transport needs."""


@dataclass(frozen=True)
class DeviceConfig:
    """One device: its kind, transport and the transport's parameters."""

    name: str
    kind: str
    protocol: str
    params: dict[str, Any]

    def get(self, key: str, default: Any = None) -> Any:
        """A transport or driver parameter."""
        return self.params.get(key, default)


@dataclass(frozen=True)
class CageConfig:
    """Which devices make the cage, and its limits."""

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


def _numbers(path: Path, where: str, value: Any, n: int) -> tuple[float, ...]:
    if (
        not isinstance(value, list)
        or len(value) != n
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise _err(path, where, f"must be a list of {n} numbers")
    return tuple(float(v) for v in value)


def _positive(path: Path, where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < math.inf:
        raise _err(path, where, "must be a positive number")
    return float(value)


def load_rig_config(path: str | Path, *, check_text: bool = True) -> RigConfig:
    """Parse and validate a rig configuration file. ``check_text=False`` skips the rule of
    :mod:`rig.text` (for ``rig safe``: an emergency stop is not refused over a device's serial)."""
    path = Path(path)
    if check_text and (problem := text_problem(str(path), label=False)) is not None:
        raise UserInputError(f"{shown(str(path), 80)}: the file's path {problem} (rename it)")
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserInputError(
            f"{path}: no such rig configuration; check the path (rig sim --rig-config writes one)"
        ) from None
    except tomllib.TOMLDecodeError as exc:
        raise UserInputError(f"{path}: not valid TOML ({exc}); fix the syntax") from None
    if check_text:
        _refuse_bad_text(path, raw, "")
    devices: dict[str, DeviceConfig] = {}
    table = raw.get("devices", {})
    if not isinstance(table, dict):
        raise _err(path, "[devices]", "must be a table of [devices.NAME] tables")
    for name, spec in table.items():
        where = f"[devices.{name}]"
        if not isinstance(spec, dict):
            raise _err(path, where, "must be a table")
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
        for param in TRANSPORTS[protocol]:
            if param.required and param.name not in spec:
                raise _err(path, where, f"needs '{param.name}' for {protocol} ({param.help})")
        for param in entry.params:
            if param.required and param.name not in spec:
                raise _err(path, where, f"needs '{param.name}' ({param.help})")
        own = {p.name: p for p in entry.param_specs(protocol)}
        known = all_params()
        for key, value in spec.items():
            if key in own:  # this transport's and kind's keys: type and accepted values
                problem = own[key].problem(value)
            elif key in known and not known[key].accepts(value):  # another kind's key: its type
                problem = f"must be {known[key].wanted}, got {value!r}"
            else:
                problem = None
            if problem is not None:
                raise _err(path, f"{where}.{key}", problem)
        params = {k: v for k, v in spec.items() if k not in ("kind", "protocol")}
        devices[name] = DeviceConfig(name, kind, protocol, params)
    cage = _cage(path, raw.get("cage"), devices) if "cage" in raw else None
    return RigConfig(path, devices, cage, raw)


def _cage(path: Path, c: Any, devices: dict[str, DeviceConfig]) -> CageConfig:
    if not isinstance(c, dict):
        raise _err(path, "[cage]", "must be a table")
    axes = c.get("axes")
    if not isinstance(axes, dict) or set(axes) != {"x", "y", "z"}:
        raise _err(
            path,
            "[cage].axes",
            'must name a supply for x, y and z: axes = { x = "...", y = "...", z = "..." }',
        )
    for ax, name in axes.items():
        if (
            not isinstance(name, str)
            or name not in devices
            or devices[name].kind not in kinds_with_role("supply")
        ):
            raise _err(
                path,
                f"[cage].axes.{ax}",
                f"'{name}' is not a supply in [devices] (kinds: {', '.join(kinds_with_role('supply'))})",
            )
    polarity = c.get("polarity")
    if polarity is not None and (
        not isinstance(polarity, str)
        or polarity not in devices
        or devices[polarity].kind not in kinds_with_role("relay")
    ):
        raise _err(
            path,
            "[cage].polarity",
            f"'{polarity}' is not a relay device in [devices] (kinds: {', '.join(kinds_with_role('relay'))})",
        )
    reference = c.get("reference")
    if reference is not None and (
        not isinstance(reference, str)
        or reference not in devices
        or devices[reference].kind not in kinds_with_role("magnetometer")
    ):
        raise _err(
            path,
            "[cage].reference",
            f"'{reference}' is not a magnetometer in [devices]"
            f" (kinds: {', '.join(kinds_with_role('magnetometer'))})",
        )
    calibration = c.get("calibration")
    if calibration is not None and not isinstance(calibration, str):
        raise _err(path, "[cage].calibration", 'must be a file name, e.g. "cage.json"')
    nominal = c.get("nominal_k_ut_per_a")
    if nominal is not None:
        if not isinstance(nominal, list) or len(nominal) != 3:
            raise _err(path, "[cage].nominal_k_ut_per_a", "must be a 3x3 list of lists (uT/A)")
        nominal = tuple(_numbers(path, "[cage].nominal_k_ut_per_a", row, 3) for row in nominal)
    return CageConfig(
        axes=(axes["x"], axes["y"], axes["z"]),
        polarity=polarity,
        reference=reference,
        calibration=(path.parent / calibration) if calibration else None,
        max_current_a=_numbers(path, "[cage].max_current_a", c.get("max_current_a"), 3),  # type: ignore[arg-type]
        max_field_ut=_positive(path, "[cage].max_field_ut", c.get("max_field_ut")),
        max_slew_a_per_s=_positive(path, "[cage].max_slew_a_per_s", c.get("max_slew_a_per_s")),
        compliance_v=_positive(path, "[cage].compliance_v", c.get("compliance_v", 20.0)),
        step_s=_positive(path, "[cage].step_s", c.get("step_s", 0.05)),
        nominal_k_ut_per_a=nominal,
    )
