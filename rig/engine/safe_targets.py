"""The outputs ``rig safe`` switches off, read from nothing but where each one is on the wire.

An emergency stop must not depend on the rest of the rig file: a ``nan`` field limit, a heater
limit of -1 or a cage table of the wrong shape has no bearing on where the supplies are. So each
``[devices.NAME]`` table is read on its own, and of it only its ``kind``, its ``protocol`` and the
keys that open it (the transport's: host, port, path, baudrate, device_id, bus, ...; the kind's
required ones: a register map); every other key and table of the file is ignored.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from drivers.registry import KINDS, TRANSPORTS
from rig.config import DeviceConfig


@dataclass(frozen=True)
class SafeTargets:
    """The output devices of a rig file that can be opened (by name, in the file's order), and
    those whose table cannot be read: name -> why, as one clause ending with the fix."""

    devices: dict[str, DeviceConfig]
    broken: dict[str, str]


def safe_targets(raw: Mapping[str, Any]) -> SafeTargets:
    """The supplies, loads and relay boards of a parsed rig file (``tomllib``'s table), each
    device on its own: one whose kind, protocol or connection keys are unusable is in
    ``broken`` and does not stop the others; devices of other kinds (magnetometers,
    thermometers) are passed over. A device of an unknown kind counts as broken: it may be an
    output."""
    devices: dict[str, DeviceConfig] = {}
    broken: dict[str, str] = {}
    table = raw.get("devices", {})
    if not isinstance(table, dict):
        return SafeTargets({}, {"[devices]": "is not a table of [devices.NAME] tables; fix it"})
    for name, spec in table.items():
        if not isinstance(spec, dict):
            broken[name] = f"[devices.{name}] is not a table; fix it"
            continue
        kind_name = spec.get("kind")
        kind = KINDS.get(kind_name) if isinstance(kind_name, str) else None
        if kind is None:
            broken[name] = (f"kind {spec.get('kind')!r} is not one of {', '.join(KINDS)};"
                            " write its kind")  # fmt: skip
            continue
        if not kind.is_output:
            continue
        protocol = spec.get("protocol")
        if not isinstance(protocol, str) or protocol not in kind.transports:
            broken[name] = (f"protocol {protocol!r} does not suit {kind.name}; write"
                            f" {' or '.join(kind.transports)}")  # fmt: skip
            continue
        connection = {t.name for t in TRANSPORTS[protocol]}
        keys = [p for p in kind.param_specs(protocol)
                if p.name in connection or (p in kind.params and p.required)]  # fmt: skip
        problems = [
            f"{p.name} missing ({p.help})" for p in keys if p.required and p.name not in spec
        ]
        problems += [f"{p.name} {why}" for p in keys if p.name in spec
                     and (why := p.problem(spec[p.name])) is not None]  # fmt: skip
        if problems:
            broken[name] = "; ".join(problems)
            continue
        params = kind.defaults(protocol) | {p.name: spec[p.name] for p in keys if p.name in spec}
        devices[name] = DeviceConfig(name, kind.name, protocol, params)
    return SafeTargets(devices, broken)
