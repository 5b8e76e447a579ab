"""Where an output device is on the wire, the same for every rig configuration that names it:
the interlock's lock keys (:mod:`rig.engine.interlock`) and the links ``rig safe`` and the guardian
switch off in parallel (:mod:`rig.engine.switch_off`)."""

from __future__ import annotations

import os
import socket

from drivers.registry import output_kinds
from rig.config import DeviceConfig, RigConfig


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
