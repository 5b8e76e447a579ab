"""Every output of a rig to its safe state and read back, each device opened on its own: ``rig
safe``, the guardian (which must act without a session: the rig process may be dead) and the
session's check of the outputs at its start and end (:mod:`rig.engine.session`).

An output is judged by what it reads back, never by what was asked of it: a supply or load is off
when its output (or load input) reads disabled and its current reads at most :data:`ON_ABOVE_A`;
a polarity relay board when every axis reads normal.

Apart from :mod:`rig.engine.session` so that the guardian, which the session starts, does not
import the session back. Its waits (retries, a coil's decay) and its thread per link are the
process's clock's (:mod:`timebase`): the wall clock for ``rig safe`` and the guardian, simulated
time for a session in it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import timebase
from drivers.registry import KINDS, output_kinds
from rig.config import DeviceConfig, RigConfig
from rig.devices import open_device
from rig.wire_address import wire_link

RETRY_FOR_S = 3.0
"""How long a device that cannot be opened is tried again when switching everything off (s): its
port may still be held by a dying rig process, which on a busy computer takes seconds to go (the
guardian once found coil_y's pty still held 0.6 s after the kill, beside two CPU hogs)."""
RETRY_PAUSE_S = 0.2
COIL_DECAY_S = 2.0
"""Longest wait for a coil's current to decay once its output is off (s), before the polarity
relays are switched (never while a coil carries current: that arcs the contacts)."""
ON_ABOVE_A = 0.01
"""A supply or load reading more current than this (A) is on, whatever its output flag says."""
DECAY_POLL_S = 0.02


@dataclass(frozen=True)
class OutputState:
    """One output as read back: ``on`` True (on), False (confirmed off) or None (not known: it
    could not be opened, switched or read, ``detail`` says why); ``current_a`` the current it
    read (A, magnitude; None for a relay board or when unread)."""

    name: str
    on: bool | None
    detail: str
    current_a: float | None = None
    done_after_s: float | None = None
    """When it was read back, from the start of the switch-off (s; its link's devices go in
    turn); None where not timed."""
    attempts: int = 1
    """Times it was opened: more than one when its port was still held or its link failed."""

    @property
    def off(self) -> bool:
        """Confirmed off by what it read back."""
        return self.on is False

    def line(self) -> str:
        """``coil_x: off (0.000 A read back)``, ``heater: ON (output enabled, 2.000 A read
        back)`` or ``load_panel: could not confirm off: <why>``."""
        if self.on is None:
            return f"{self.name}: could not confirm off: {self.detail}"
        return f"{self.name}: {'ON' if self.on else 'off'} ({self.detail})"

    def short(self) -> str:
        """``coil_x 0.000 A``, ``polarity normal``, ``heater unread (<why>)``: for one line
        listing every output."""
        if self.on is None:
            return f"{self.name} unread ({self.detail})"
        if self.current_a is None:
            return f"{self.name} {self.detail}"
        enabled = " (output enabled)" if self.detail.startswith("output enabled") else ""
        return f"{self.name} {self.current_a:.3f} A{enabled}"


def output_devices_of(cfg: RigConfig) -> dict[str, DeviceConfig]:
    """The supplies, loads and relay boards of ``cfg`` (by name)."""
    kinds = output_kinds()
    return {n: d for n, d in cfg.devices.items() if d.kind in kinds}


def switch_off_every_output(cfg: RigConfig) -> tuple[list[str], list[str], str]:
    """Every supply, load and relay board of ``cfg`` to its safe state and read back
    (:func:`switch_off_and_confirm`): (devices confirmed off, one problem line for each other,
    :func:`slowest_note`)."""
    states = switch_off_and_confirm(output_devices_of(cfg))
    done = [n for n, s in states.items() if s.off]
    problems = [f"{n}: {s.detail}" + (" (still on)" if s.on else "")
                for n, s in states.items() if not s.off]  # fmt: skip
    return done, problems, slowest_note(states.values())


SLOW_NOTE_S = 0.3
"""A switch-off whose slowest output took longer than this (s) names it."""


def slowest_note(states: Iterable[OutputState]) -> str:
    """``; slowest: coil_y read back off after 1412 ms, opened at attempt 3`` when the slowest
    output took longer than :data:`SLOW_NOTE_S`, else ``""``: where a slow time to safe went."""
    timed = [(s.done_after_s, s) for s in states if s.done_after_s is not None]
    if not timed:
        return ""
    after_s, slow = max(timed, key=lambda pair: pair[0])
    if after_s <= SLOW_NOTE_S:
        return ""
    opened = f", opened at attempt {slow.attempts}" if slow.attempts > 1 else ""
    return f"; slowest: {slow.name} read back after {1000.0 * after_s:.0f} ms{opened}"


def switch_off_and_confirm(
    devices: Mapping[str, DeviceConfig], unreachable: Sequence[str] = ()
) -> dict[str, OutputState]:
    """Every output of ``devices`` (supplies, loads, relay boards; other kinds are passed over)
    to its safe state, each opened on its own (one dead link does not stop the others), then
    read back: name -> state, in the order of ``devices``.

    Supplies and loads first, one thread per link (devices sharing a serial bus or a TCP
    endpoint take turns on it), so a slow or dead link does not hold back the others: the time
    to safe is the slowest link's, not the sum; each is read back once its current has decayed
    (at most :data:`COIL_DECAY_S`). Then the polarity relays to normal, only when every supply and
    load read back off and none is ``unreachable`` (outputs known by name only, e.g. whose
    configuration cannot be read: they may be coils carrying current); otherwise a relay board
    is only read, and one that reads reversed is left as it is (switching a coil that may carry
    current arcs the contacts)."""
    kinds = output_kinds()
    outputs = {n: d for n, d in devices.items() if d.kind in kinds}
    supplies = {n: d for n, d in outputs.items() if not _is_relay(d)}
    relays = {n: d for n, d in outputs.items() if n not in supplies}
    states = _per_link(supplies, lambda d: _act(d, switch=True, retry_s=RETRY_FOR_S))
    carrying = [s.short() for s in states.values() if not s.off]
    carrying += [f"{n} unread" for n in unreachable]
    for name, dev in relays.items():
        if not carrying:
            states[name] = _act(dev, switch=True, retry_s=RETRY_FOR_S)
            continue
        state = _act(dev, switch=False, retry_s=RETRY_FOR_S)
        if state.on:
            state = OutputState(name, None, f"{state.detail}, left as it is as {'; '.join(carrying)}"
                                " may carry current (switch it when the coils are off)")  # fmt: skip
        states[name] = state
    return {n: states[n] for n in outputs}


def read_outputs(
    devices: Mapping[str, DeviceConfig], retry_s: float = 0.0
) -> dict[str, OutputState]:
    """Read every output of ``devices`` as it is, touching nothing: one thread per link, each
    device opened, read and closed (tried again for ``retry_s``, s); a current still decaying
    through an output that reads off is waited for (:data:`COIL_DECAY_S`). Name -> state."""
    kinds = output_kinds()
    outputs = {n: d for n, d in devices.items() if d.kind in kinds}
    states = _per_link(outputs, lambda d: _act(d, switch=False, retry_s=retry_s))
    return {n: states[n] for n in outputs}


def switch_off_found_on(
    devices: Mapping[str, DeviceConfig], retry_s: float
) -> tuple[list[str], str | None]:
    """Read every output of ``devices`` (each tried again for ``retry_s``, s) and switch off each
    one found on: (one line per output found on, saying what it read and what it read back after
    the switch-off; the line of the first output that could not be read or confirmed off, or
    None)."""
    found = read_outputs(devices, retry_s=retry_s)
    on = {n: devices[n] for n, s in found.items() if s.on}
    unread = [n for n, s in found.items() if s.on is None]
    after = switch_off_and_confirm(on, unreachable=unread) if on else {}
    lines = [f"{name} was found on at the start ({found[name].detail}); switched off before"
             f" anything else, read back: {after[name].line()}" for name in on]  # fmt: skip
    bad = [s for s in found.values() if s.on is None] + [s for s in after.values() if not s.off]
    return lines, (bad[0].line() if bad else None)


def read_back_and_off(devices: Mapping[str, DeviceConfig]) -> dict[str, OutputState]:
    """Every output of ``devices`` read back; one found on or unread is switched off (and read
    back) again. Never raises: what could not be read says so in its state."""
    try:
        states = read_outputs(devices)
        again = {n: devices[n] for n, s in states.items() if not s.off}
        if again:
            states |= switch_off_and_confirm(again)
    except Exception as exc:  # the safe path never raises: say what is not known
        states = {n: OutputState(n, None, f"not read back ({exc})") for n in devices}
    return states


def _is_relay(dev: DeviceConfig) -> bool:
    """A relay board (the ``relay`` role), not a supply or load."""
    kind = KINDS.get(dev.kind)
    return kind is not None and "relay" in kind.roles and not ({"supply", "load"} & kind.roles)


def _per_link(
    devices: Mapping[str, DeviceConfig], act: Callable[[DeviceConfig], OutputState]
) -> dict[str, OutputState]:
    """``act`` on every device, one thread per link, the devices of a link in turn."""
    links: dict[str, list[DeviceConfig]] = {}
    for dev in devices.values():
        links.setdefault(wire_link(dev), []).append(dev)
    states: dict[str, OutputState] = {}
    results: list[list[OutputState] | BaseException] = [[] for _ in links]

    t0 = timebase.monotonic()

    def on_link(i: int, devs: list[DeviceConfig]) -> None:
        try:
            results[i] = [replace(act(d), done_after_s=timebase.monotonic() - t0) for d in devs]
        except BaseException as exc:  # raised in the caller, as a pool's map would
            results[i] = exc

    threads = [timebase.Thread(on_link, name=f"safe-{i}", args=(i, devs))
               for i, devs in enumerate(links.values())]  # fmt: skip
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for found in results:
        if isinstance(found, BaseException):
            raise found
        states.update((s.name, s) for s in found)
    return states


def _act(dev: DeviceConfig, *, switch: bool, retry_s: float) -> OutputState:
    """Open ``dev``, call its ``safe()`` when ``switch``, read it back and close it, tried again
    for ``retry_s`` (s) when any of it fails (a port still held by a dying process)."""
    deadline = timebase.monotonic() + retry_s
    attempts = 0
    while True:
        attempts += 1
        try:
            driver = open_device(dev)
            try:
                if switch:
                    driver.safe()
                return replace(_read_back(dev.name, driver), attempts=attempts)
            finally:
                driver.close()
        except Exception as exc:  # one dead link must not stop the others going safe
            if timebase.monotonic() >= deadline:
                did = "switching it off" if switch else "reading it"
                return OutputState(dev.name, None, f"{did} at {dev.where} failed ({exc})",
                                   attempts=attempts)  # fmt: skip
            timebase.sleep(RETRY_PAUSE_S)


def _read_back(name: str, driver: Any) -> OutputState:
    """The state ``driver`` reads: a relay board's axes, or a supply's or load's output flag and
    current (when its output reads off, waiting up to :data:`COIL_DECAY_S` for a coil's current to
    decay: a current that does not is on)."""
    if not hasattr(driver, "read"):
        polarity = getattr(driver, "polarity", None)
        if polarity is None:  # a relay board that cannot say: its safe() is all there is
            return OutputState(name, False, "switched to normal, its state cannot be read")
        reversed_axes = [ax for i, ax in enumerate("xyz") if polarity(i) != 1]
        if reversed_axes:
            return OutputState(name, True, f"reversed on {', '.join(reversed_axes)}")
        return OutputState(name, False, "normal")
    deadline = timebase.monotonic() + COIL_DECAY_S
    while True:
        r = driver.read()
        amps = abs(float(r.i_out_a))
        if r.output_on or amps <= ON_ABOVE_A:
            break
        if timebase.monotonic() > deadline:
            break
        timebase.sleep(DECAY_POLL_S)
    on = bool(r.output_on) or amps > ON_ABOVE_A
    enabled = "output enabled, " if r.output_on else ""
    return OutputState(name, on, f"{enabled}{amps:.3f} A read back", amps)
