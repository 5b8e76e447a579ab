"""Where a device is on the wire, the same for every rig configuration that names it:
the interlock's lock keys (:mod:`rig.engine.interlock`), the links ``rig safe`` and the guardian
switch off in parallel (:mod:`rig.engine.switch_off`), and what every output's limits and cage role
key on (:mod:`rig.output_limits`): never a device's name, so a second name for one instrument
cannot reach it without them, and a configuration that gives one two names is refused
(:func:`shared_addresses`)."""

from __future__ import annotations

import os
import socket

from drivers.registry import output_kinds
from rig.config import DeviceConfig, RigConfig
from rig.errors import UserInputError


def wire_link(dev: DeviceConfig) -> str:
    """The wire a device is on (a TCP endpoint, a serial port, an I2C bus), the same for every
    configuration that names it: devices on one link take turns on it."""
    if dev.protocol == "modbus-tcp":
        return f"modbus-tcp {dev.get('host')}:{dev.get('port', 502)}"
    if dev.protocol == "modbus-rtu":
        path = str(dev.get("path"))
        if "://" not in path:
            path = os.path.realpath(path)  # /dev/serial/by-id/... and /dev/ttyUSB0 are one port
        return f"modbus-rtu {path}"
    if dev.protocol == "i2c":
        return f"i2c bus {dev.get('bus', 1)}"
    return f"{dev.protocol} {os.path.realpath(str(dev.get('path')))}"


def wire_address(dev: DeviceConfig) -> str:
    """Where a device is on the wire, the same for every configuration that names it."""
    if dev.protocol in ("modbus-tcp", "modbus-rtu"):
        return f"{wire_link(dev)} id {dev.get('device_id', 1)}"
    if dev.protocol == "i2c":
        return f"{wire_link(dev)} address {int(dev.get('address')):#04x}"
    return wire_link(dev)


def numeric_hosts(host: str, port: int) -> tuple[str, ...]:
    """Every numeric address ``host`` resolves to (``getaddrinfo``), sorted; the name itself, in
    lower case, when it does not resolve (the connection will say so)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError, ValueError):
        return (host.lower(),)
    found = {str(info[4][0]) for info in infos}
    return tuple(sorted(found)) or (host.lower(),)


def lock_addresses(dev: DeviceConfig) -> tuple[str, ...]:
    """The wire addresses the interlock locks for ``dev``: :func:`wire_address`, with a TCP
    host resolved to each of its numeric addresses, so aliases of one supply share its lock."""
    if dev.protocol != "modbus-tcp":
        return (wire_address(dev),)
    port = int(dev.get("port", 502))
    return tuple(
        f"modbus-tcp {f'[{a}]' if ':' in a else a}:{port} id {dev.get('device_id', 1)}"
        for a in numeric_hosts(str(dev.get("host")), port)
    )


def output_devices(cfg: RigConfig) -> dict[str, tuple[str, ...]]:
    """The output devices of ``cfg`` (name -> lock addresses): what the interlock locks."""
    kinds = output_kinds()
    return {name: lock_addresses(d) for name, d in cfg.devices.items() if d.kind in kinds}


def device_addresses(cfg: RigConfig) -> dict[str, tuple[str, ...]]:
    """Every device of ``cfg`` (name -> its wire addresses, TCP hosts resolved as the interlock
    resolves them)."""
    return {name: lock_addresses(d) for name, d in cfg.devices.items()}


def same_device(cfg: RigConfig, a: str, b: str) -> bool:
    """Do devices ``a`` and ``b`` of ``cfg`` reach one instrument on the wire (one name, or two
    names for one address: ``localhost`` and ``127.0.0.1``, a by-id link and its tty)?"""
    if a == b:
        return True
    if a not in cfg.devices or b not in cfg.devices:
        return False
    return bool(set(lock_addresses(cfg.devices[a])) & set(lock_addresses(cfg.devices[b])))


def shared_addresses(cfg: RigConfig) -> list[str]:
    """One sentence per wire address that two or more devices of ``cfg`` name, one of them an
    output (supply, load, relay), with the fix: a second name for one output would reach it
    without the first one's limits and roles. (Sensors sharing a placeholder path, as dry-run
    configurations write ``/dev/null``, drive nothing.)"""
    seen: dict[str, list[str]] = {}
    for name, addresses in device_addresses(cfg).items():
        for address in addresses:
            seen.setdefault(address, []).append(name)
    outputs = output_kinds()
    out, told = [], set()
    for address, names in seen.items():
        key = tuple(names)
        if len(names) < 2 or key in told or all(cfg.devices[n].kind not in outputs for n in names):
            continue
        told.add(key)
        listed = " and ".join(f"[devices.{n}]" for n in names)
        out.append(f"{cfg.path}: {listed} are one instrument ({address}): a second name would"
                   f" drive it without {names[0]}'s limits; keep one table for it")  # fmt: skip
    return out


def refuse_shared_addresses(cfg: RigConfig) -> None:
    """Refuse (UserInputError, one line) a configuration naming one instrument twice."""
    problems = shared_addresses(cfg)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise UserInputError(problems[0] + more)
