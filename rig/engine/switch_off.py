"""Every output of a rig to its safe state, each device opened on its own: ``rig safe`` and the
guardian (which must act without a session: the rig process may be dead).

Apart from :mod:`rig.engine.session` so that the guardian, which the session starts, does not
import the session back.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

from drivers.registry import output_kinds
from rig.config import DeviceConfig, RigConfig
from rig.devices import open_device
from rig.wire_address import wire_link

RETRY_FOR_S = 3.0
"""How long a device that cannot be opened is tried again when switching everything off (s): its
port may still be held by a dying rig process, which on a busy computer takes seconds to go (the
guardian once found coil_y's pty still held 0.6 s after the kill, beside two CPU hogs)."""
RETRY_PAUSE_S = 0.2
COIL_DECAY_S = 2.0
"""Longest wait for a coil's current to decay before its polarity relay is switched."""


def switch_off_every_output(cfg: RigConfig) -> tuple[list[str], list[str]]:
    """Every supply, load and relay board of ``cfg`` to its safe state, each opened on its own
    (one dead link does not stop the others): (devices switched off, problems).

    Supplies and loads first, one thread per link (devices sharing a serial bus or a TCP
    endpoint take turns on it), so a slow or dead link does not hold back the others: the time
    to safe is the slowest link's, not the sum. Then, once the cage's coil currents have
    decayed, the polarity relays to normal (never switched while a coil carries current: that
    arcs the contacts)."""
    kinds = output_kinds()
    outputs = [(n, d) for n, d in cfg.devices.items() if d.kind in kinds]
    supplies = [(n, d) for n, d in outputs if d.kind != "relay"]
    relays = [(n, d) for n, d in outputs if d.kind == "relay"]
    links: dict[str, list[tuple[str, DeviceConfig]]] = {}
    for name, dev in supplies:
        links.setdefault(wire_link(dev), []).append((name, dev))
    outcome: dict[str, str | None] = {}
    with ThreadPoolExecutor(max_workers=max(1, len(links)), thread_name_prefix="safe") as pool:
        for results in pool.map(lambda devs: [(n, _switch_off(d)) for n, d in devs],
                                links.values()):  # fmt: skip
            outcome.update(results)
    for name, dev in relays:
        still = _coil_currents_above(cfg, 0.02)
        outcome[name] = (
            _switch_off(dev)
            if not still
            else f"left as it is, {still} (switch it when the coils are off)"
        )
    done = [n for n, _ in supplies + relays if outcome[n] is None]
    problems = [f"{n}: {outcome[n]}" for n, _ in supplies + relays if outcome[n] is not None]
    return done, problems


def _switch_off(dev: DeviceConfig) -> str | None:
    """Open ``dev``, call its ``safe()`` and close it, tried again for :data:`RETRY_FOR_S`: None
    when it is safe, else the last error."""
    deadline = time.monotonic() + RETRY_FOR_S
    while True:
        try:
            driver = open_device(dev)
            try:
                driver.safe()
            finally:
                driver.close()
            return None
        except Exception as exc:  # one dead link must not stop the others going safe
            if time.monotonic() >= deadline:
                return str(exc)
            time.sleep(RETRY_PAUSE_S)  # a port still held by someone else


def _coil_currents_above(cfg: RigConfig, threshold_a: float) -> str:
    """Wait up to COIL_DECAY_S for every coil's current to fall below ``threshold_a``; '' when it
    has, else which coil still carries what (a coil that cannot be read counts as carrying)."""
    if cfg.cage is None:
        return ""
    deadline = time.monotonic() + COIL_DECAY_S
    left = list(cfg.cage.axes)
    while True:
        carrying = []
        for name in left:
            try:
                supply = open_device(cfg.devices[name])
                try:
                    amps = abs(float(supply.read().i_out_a))
                finally:
                    supply.close()
            except Exception as exc:  # unknown: assume it carries
                carrying.append(f"{name} unreadable ({exc})")
                continue
            if amps > threshold_a:
                carrying.append(f"{name} carries {amps:.3f} A")
        if not carrying or time.monotonic() > deadline:
            return "; ".join(carrying)
        time.sleep(0.05)
