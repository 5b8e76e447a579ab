"""A rig session: the devices one command drives, opened for the command's lifetime, and the safe
state of every output on every way out (normal end, error, Ctrl-C, SIGTERM).

    with RigSession(cfg) as rig:
        controller = rig.cage()              # coil supplies, relays, reference, limits
        bus = rig.load("load_bus")           # at 0 A, output on
        dut = rig.magnetometer("dut")
        ...                                  # leaving the block: coils ramped down, every
                                             # output off, then the links closed

Every command that drives outputs (``rig run`` and ``rig demo`` through the runner, ``rig cage
...``) opens its devices here; ``rig safe`` and the guardian use :func:`switch_off_every_output`.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from contextlib import ExitStack
from types import TracebackType
from typing import Any, cast

from drivers.errors import DeviceError
from drivers.protocols import Load, Magnetometer
from drivers.registry import output_kinds
from rig.cage.controller import CageController
from rig.config import RigConfig
from rig.devices import build_cage, open_device, open_load, open_magnetometer
from rig.errors import UserInputError

ATTEMPTS = 3
"""Tries per device when switching everything off (a port may still be held by a dying process)."""


def _warn(message: str) -> None:
    print(f"rig: WARNING: {message}; switch it off by hand", file=sys.stderr)


class RigSession:
    """The cage controller, load channels and magnetometers of one command, closed together.

    ``on_unsafe`` is told (one line each) about any output that may still be on after
    :meth:`safe`; by default it is printed to stderr, whatever the verbosity.
    """

    def __init__(self, cfg: RigConfig, *, i2c_bus: Any | None = None,
                 on_unsafe: Callable[[str], None] = _warn) -> None:  # fmt: skip
        self.cfg = cfg
        self.i2c_bus = i2c_bus
        self.on_unsafe = on_unsafe
        self.controller: CageController | None = None
        self.loads: dict[str, Load] = {}
        self.magnetometers: dict[str, Magnetometer] = {}
        self._stack = ExitStack()

    def __enter__(self) -> RigSession:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            self.safe()
        finally:
            self._stack.close()

    def _device(self, name: str, what: str) -> Any:
        dev = self.cfg.devices.get(name)
        if dev is None:
            raise UserInputError(
                f"{self.cfg.path}: no device '{name}' for the {what}; devices are: {', '.join(self.cfg.devices)}"
            )
        return dev

    def cage(self) -> CageController:
        """The cage controller (opened on first use): its supplies, relays and reference."""
        if self.controller is None:
            self.controller = build_cage(self.cfg, self._stack, self.i2c_bus)
        return self.controller

    def load(self, name: str) -> Load:
        """Load channel ``name`` at 0 A with its output on; switched off when the session ends."""
        if name not in self.loads:
            load = open_load(self._device(name, "load"), self.i2c_bus)
            self._stack.callback(load.close)
            self.loads[name] = load
        return self.loads[name]

    def magnetometer(self, name: str) -> Magnetometer:
        """Magnetometer ``name``; the cage's reference is the one the controller already holds."""
        cage, ctl = self.cfg.cage, self.controller
        if ctl is not None and ctl.reference is not None and cage and name == cage.reference:
            return cast(Magnetometer, ctl.reference)  # opened by build_cage as a magnetometer
        if name not in self.magnetometers:
            mag = open_magnetometer(self._device(name, "magnetometer"), self.i2c_bus)
            self._stack.callback(mag.close)
            self.magnetometers[name] = mag
        return self.magnetometers[name]

    def on_close(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run ``fn(*args)`` when the session ends, after the safe state and before the links
        close (last registered, first run)."""
        self._stack.callback(fn, *args)

    def safe(self) -> list[str]:
        """Coils ramped down and off, then every load off; never raises (idempotent). Returns
        what may still be on, each also told to ``on_unsafe``."""
        problems = []
        if self.controller is not None:
            problems += [f"cage did not go fully safe: {p}" for p in self.controller.safe()]
        for name, load in self.loads.items():
            try:
                load.safe()
            except (DeviceError, OSError) as exc:
                problems.append(f"load {name} did not go safe: {exc}")
        for p in problems:
            self.on_unsafe(p)
        return problems


def switch_off_every_output(cfg: RigConfig) -> tuple[list[str], list[str]]:
    """Every supply, load and relay board of ``cfg`` to its safe state, each opened on its own
    (one dead link does not stop the others): (devices switched off, problems)."""
    done: list[str] = []
    problems: list[str] = []
    kinds = output_kinds()
    for name, dev in cfg.devices.items():
        if dev.kind not in kinds:
            continue
        for attempt in range(ATTEMPTS):
            try:
                driver = open_device(dev)
                try:
                    driver.safe()
                finally:
                    driver.close()
                done.append(name)
                break
            except Exception as exc:  # one dead link must not stop the others going safe
                if attempt == ATTEMPTS - 1:
                    problems.append(f"{name}: {exc}")
                else:
                    time.sleep(0.3)  # a port still held by someone else
    return done, problems
