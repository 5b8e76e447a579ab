"""Every simulated device kind, by the name the simulator's TOML gives it: the one place a new one
is registered (ADR 0022). To add one, write its module with a :class:`sim.device_kind.SimKind`
and add it to the tuple below (docs/architecture.md)."""

from __future__ import annotations

from sim import ascii_mag, cesium, hmr2300, lis3mdl, modbus_devices, rm3100
from sim.device_kind import Section, SimKind

KINDS: dict[tuple[Section, str], SimKind] = {
    (k.section, k.name): k
    for k in (
        modbus_devices.RIDEN,
        modbus_devices.REGMAP,
        hmr2300.KIND,
        ascii_mag.KIND,
        cesium.KIND,
        rm3100.KIND,
        lis3mdl.KIND,
    )
}


def sim_kind(section: Section, name: str, device: str) -> SimKind:
    """The kind ``name`` in ``section``; an unknown one is a one-line error naming ``device``."""
    try:
        return KINDS[(section, name)]
    except KeyError:
        known = ", ".join(k for s, k in KINDS if s == section)
        raise ValueError(f"{section} '{device}': unknown kind '{name}' (one of {known})") from None
