"""A rig session: the devices one command drives, opened for the command's lifetime, and the safe
state of every output on every way out (normal end, error, Ctrl-C, SIGTERM).

    with RigSession(cfg) as rig:
        controller = rig.cage()              # coil supplies, relays, reference, limits
        bus = rig.load("load_bus")           # at 0 A, output on
        dut = rig.magnetometer("dut")
        ...                                  # leaving the block: coils ramped down, every
                                             # output off, then the links closed

Every command that drives outputs (``rig run`` and ``rig demo`` through the runner, ``rig cage
...``) opens its devices here, and the session owns the safety around them:

* the interlock (rig.engine.interlock): no second command drives the same outputs meanwhile;
* the guardian process (rig.engine.guardian), given the configuration as parsed here and fed a
  heartbeat while the main thread makes progress: it switches every output off if this process
  dies or hangs; watched in turn, a guardian that dies or is stopped is a fault. In simulated
  time there is none (:data:`NO_GUARDIAN_SIMULATED`: the simulated outputs live and die with this
  process), and :attr:`RigSession.no_guardian` says why;
* the outputs as found: at its start, once it holds the interlock and the guardian runs, every
  output of the configuration (not only those the command opens) is read; one found on (its
  output enabled, a current, a relay reversed: a rig and guardian that both died) is reported
  (``on_found_on``, :attr:`RigSession.found_on`) and switched off before anything else, and one
  that cannot be read or confirmed off refuses the command in one line;
* the outputs as left: at its end, after the safe path and once its links are closed, every
  output is read back (:attr:`RigSession.read_back`): the end of a run states what was read,
  never what was assumed;
* the last configuration used: the raw text of the rig file, kept in the lock folder
  (:mod:`rig.engine.config_copy`) for ``rig safe`` should the file later not parse;
* fault-aware waiting: every wait while outputs are live (the cage controller's ramps, relay
  flips, trim, characterization, holds) goes through :meth:`RigSession.sleep`, which raises the
  first fault reported by any thread (:meth:`RigSession.fail`) or an abort.

``rig safe`` and the guardian use :func:`rig.engine.switch_off.switch_off_every_output` (re-exported
here); the session alone takes the outputs of a command to the safe state (:meth:`RigSession.safe`,
once, as it ends; ADR 0012, ADR 0023).
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from types import TracebackType
from typing import Any, cast

import timebase
from drivers.errors import DeviceError
from drivers.protocols import Load, Magnetometer, ScalarMagnetometer, Thermometer
from rig.cage.controller import SAFE_TIMEOUT_S, CageController
from rig.config import RigConfig
from rig.devices import (
    build_cage,
    open_load,
    open_magnetometer,
    open_scalar_magnetometer,
    open_thermometer,
)
from rig.engine.config_copy import keep_config_copy
from rig.engine.cpu_wait import run_delay_s
from rig.engine.guardian import HEARTBEAT_PERIOD_S, Guardian
from rig.engine.interlock import RigLock
from rig.engine.switch_off import (
    OutputState,
    output_devices_of,
    read_back_and_off,
    switch_off_found_on,
)
from rig.engine.switch_off import switch_off_every_output as switch_off_every_output
from rig.errors import RigError, RunAborted, UserInputError

MAIN_THREAD_STALL_S = 15.0
"""The main thread made no progress for this long (outside an operator prompt): it is deadlocked
or lost, and the heartbeat stops, so the guardian takes the outputs to the safe state. Longer
than any single blocking call of a healthy run (a Modbus transaction with its retries, a batch
calibration of a long run)."""
READ_RETRY_S = 1.0
"""How long an output that does not answer at the session's start is tried again (s)."""
NO_GUARDIAN_SIMULATED = (
    "no guardian process: in simulated time the simulated cage lives inside this process (its"
    " wires are in-process pipes no other process can open), so its outputs end with it"
)


def _warn(message: str) -> None:
    print(f"rig: WARNING: {message}; switch it off by hand", file=sys.stderr)


def _tell_found_on(message: str) -> None:
    print(f"rig: WARNING: {message}", file=sys.stderr)


class RigSession:
    """The cage controller, load channels and magnetometers of one command, closed together.

    ``on_unsafe`` is told (one line each) about any output that may still be on after
    :meth:`safe` or reads back on at the end; ``on_found_on`` about each output found on at the
    start and switched off; by default both are printed to stderr, whatever the verbosity.
    """

    def __init__(self, cfg: RigConfig, *, command: str = "rig", folder: Path | None = None,
                 guardian: bool = True, lock: RigLock | None = None, i2c_bus: Any | None = None,
                 abort: threading.Event | None = None,
                 on_unsafe: Callable[[str], None] = _warn,
                 on_found_on: Callable[[str], None] = _tell_found_on) -> None:  # fmt: skip
        self.cfg = cfg
        self.command = command
        self.folder = folder
        self.use_guardian = guardian
        self.lock = lock
        self.i2c_bus = i2c_bus
        self.abort = abort if abort is not None else timebase.Event()
        self.on_unsafe = on_unsafe
        self.on_found_on = on_found_on
        self.found_on: list[str] = []
        """One line per output found on at the start (and switched off)."""
        self.read_back: dict[str, OutputState] | None = None
        """Every output as read back at the end (None until the session has ended)."""
        self.controller: CageController | None = None
        self.loads: dict[str, Load] = {}
        self.magnetometers: dict[str, Magnetometer] = {}
        self.fault: str | None = None
        self.fault_at: float | None = None  # monotonic s when it was reported
        self._faulted = timebase.Event()  # set with the first fault: wakes fault-aware waits
        self.guardian: Guardian | None = None
        self.no_guardian: str | None = None
        """Why no guardian was started although one was asked for (simulated time), else None."""
        self._stack = ExitStack()
        self._progress_s = timebase.monotonic()
        self._operator_waits = 0
        # the heartbeat is the guardian's, a real process's: on the wall clock like it
        self._beating = threading.Event()
        self._heart: threading.Thread | None = None

    def __enter__(self) -> RigSession:
        """Take the interlock, keep a copy of the configuration, start the guardian and its
        heartbeat, then switch off every output found on (:meth:`_outputs_as_found`)."""
        if self.lock is None:
            self.lock = RigLock(self.cfg, self.command)
        if not self.lock.held:
            self.lock.acquire()
        try:
            keep_config_copy(self.cfg.path, self.cfg.raw)
            if self.use_guardian and timebase.is_simulated():
                self.no_guardian = NO_GUARDIAN_SIMULATED
            elif self.use_guardian:
                self.guardian = Guardian(self.cfg, self.folder, tuple(self.lock.fds))
                self._beating.set()
                self._heart = threading.Thread(target=self._beat, name="heartbeat", daemon=True)
                self._heart.start()
            self._outputs_as_found()
        except BaseException:
            self._stop_guardian()
            self.lock.release()
            raise
        return self

    def _outputs_as_found(self) -> None:
        """Switch off every output of the configuration found on, telling ``on_found_on``
        (:func:`switch_off_found_on`); raise :class:`RigError` (one line with the fix) naming
        one that cannot be read or confirmed off, the others left safe."""
        lines, bad = switch_off_found_on(output_devices_of(self.cfg), READ_RETRY_S)
        for line in lines:
            self.found_on.append(line)
            self.on_found_on(line)
        if bad is not None:
            raise RigError(
                f"{self.cfg.path}: {bad}; nothing was started: check its power and"
                f" wiring, then run 'rig safe --rig {self.cfg.path}' and start again"
            )

    def _stop_guardian(self) -> None:
        """Stop the heartbeat and let the guardian go (a clean exit)."""
        self._beating.clear()
        if self._heart is not None:
            self._heart.join(2 * HEARTBEAT_PERIOD_S + 1.0)
        if self.guardian is not None:
            self.guardian.release()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            self.safe()
        finally:
            try:
                try:
                    self._stack.close()
                finally:
                    self.read_back = self._read_back()
            finally:
                self._stop_guardian()
                if self.lock is not None:
                    self.lock.release()

    def _read_back(self) -> dict[str, OutputState]:
        """Every output read back once the links are closed (:func:`read_back_and_off`); each
        that does not read back off goes to ``on_unsafe``. Never raises."""
        states = read_back_and_off(output_devices_of(self.cfg))
        for state in states.values():
            if not state.off:
                self.on_unsafe(state.line())
        return states

    # --- liveness, faults and waiting -------------------------------------------------------------

    def _beat(self) -> None:
        """Heartbeat to the guardian while the main thread makes progress (or waits for the
        operator); silent once it has been stuck for MAIN_THREAD_STALL_S. Between beats it
        watches the guardian: one that dies or is stopped is a fault (:meth:`fail`), so the
        outputs go safe through the normal exit path rather than run on unguarded."""
        assert self.guardian is not None
        told = False
        main_tid = threading.main_thread().native_id
        seen_progress, waited_at_progress = self._progress_s, run_delay_s(main_tid)
        while self._beating.is_set():
            # time the main thread was ready to run but had no CPU (a busy computer) is not
            # its being stuck: a batch fit that takes 3 s alone takes 20 s beside two CPU hogs
            waited_s = run_delay_s(main_tid)
            if self._progress_s != seen_progress:
                seen_progress, waited_at_progress = self._progress_s, waited_s
            stuck_s = timebase.monotonic() - seen_progress - (waited_s - waited_at_progress)
            if self._operator_waits or stuck_s < MAIN_THREAD_STALL_S:
                self.guardian.beat()  # a failed write means it is gone: gone() below says how
            elif not told:
                told = True
                print(f"rig: ERROR: no progress for {stuck_s:.0f} s; the guardian switches the"
                      " outputs off", file=sys.stderr)  # fmt: skip
            how = self.guardian.gone(HEARTBEAT_PERIOD_S)  # the period's wait; at once if it dies
            if how is not None and self._beating.is_set():
                self.fail(f"the guardian process {how}; outputs switched off, as nothing"
                          " would switch them off if rig died too: find what ended or stopped"
                          " it (the system log: an out-of-memory kill) and start again")  # fmt: skip
                return

    def fail(self, message: str) -> None:
        """Report a fault from any thread: the next fault-aware wait raises it (first one wins)."""
        if self.fault is None:
            self.fault_at = timebase.monotonic()
            self.fault = message
            self._faulted.set()

    def check(self) -> None:
        """The main thread is alive; raise the reported fault, or RunAborted after an abort."""
        self._progress_s = timebase.monotonic()
        if self.fault is not None:
            raise RigError(self.fault)
        if self.abort.is_set():
            raise RunAborted("aborted")

    @property
    def interrupts(self) -> tuple[threading.Event, ...]:
        """The events that end a fault-aware wait: the abort, and the first fault reported."""
        return (self.abort, self._faulted)

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` (0 just checks), raising a fault or abort as soon as it is reported
        (on the wall clock within ``timebase.clock.POLL_S``, in simulated time at once)."""
        end = timebase.monotonic() + seconds
        while True:
            self.check()
            remaining = end - timebase.monotonic()
            if remaining <= 0:
                return
            timebase.wait_any(self.interrupts, remaining)

    @contextlib.contextmanager
    def waiting_for_operator(self) -> Iterator[None]:
        """Inside, the main thread may block for as long as the operator takes to answer."""
        self._operator_waits += 1
        try:
            yield
        finally:
            self._operator_waits -= 1
            self._progress_s = timebase.monotonic()

    def check_coils(
        self,
        record: Callable[[float, str, float], None] | None = None,
        on_unread: Callable[[str, Exception], None] | None = None,
    ) -> None:
        """Read every coil supply of an enabled cage once; a tripped supply is a fault
        (:meth:`fail`). ``record(t_asked, channel, signed A)`` gets each reading; a supply that
        does not answer goes to ``on_unread(channel, error)``, or raises without it."""
        ctl = self.controller
        if ctl is None or not ctl.enabled:
            return
        for axis, drive in enumerate(ctl.axes):
            channel = f"coil_{'xyz'[axis]}"
            t_asked = timebase.monotonic()  # the reading is from after this
            try:
                reading = drive.supply.read()
            except (DeviceError, OSError) as exc:
                if on_unread is None:
                    raise
                on_unread(channel, exc)
                continue
            if record is not None:  # the supply reads an unsigned current; a relay gives its sign
                sign = 1 if drive.bipolar else ctl.signs[axis]
                record(t_asked, channel, sign * float(reading.i_out_a))
            if reading.protection:
                self.fail(f"coil {'xyz'[axis]} supply tripped ({reading.protection}) and is off;"
                          " check the coil wiring, then run again")  # fmt: skip

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
            # its safe state is this session's to reach (:meth:`safe`), not the stack's
            self.controller = build_cage(self.cfg, self._stack, self.i2c_bus, safe_on_exit=False)
            self.controller.sleep = self.sleep  # its ramps, flips and trims see faults
        return self.controller

    def load(self, name: str) -> Load:
        """Load channel ``name`` at 0 A with its output on; switched off when the session ends."""
        if name not in self.loads:
            load = open_load(self._device(name, "load"), self.i2c_bus, self.cfg)
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

    def scalar_magnetometer(self, name: str) -> ScalarMagnetometer:
        """Total-field magnetometer ``name`` (closed when the session ends)."""
        scalar = open_scalar_magnetometer(self._device(name, "scalar"))
        self._stack.callback(scalar.close)
        return scalar

    def thermometer(self, name: str) -> Thermometer:
        """Thermometer ``name`` (closed when the session ends)."""
        thermometer = open_thermometer(self._device(name, "thermometer"), self.i2c_bus)
        self._stack.callback(thermometer.close)
        return thermometer

    def on_close(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run ``fn(*args)`` when the session ends, after the safe state and before the links
        close (last registered, first run)."""
        self._stack.callback(fn, *args)

    def safe(self) -> list[str]:
        """Coils ramped down and off, every load off, then the polarity relays to normal once
        the coils have decayed (a coil that cannot be read may take COIL_DECAY_S: every output
        is off by then); never raises (idempotent). Returns what may still be on, each also told
        to ``on_unsafe``."""
        problems: list[str] = []

        def load_off(name: str, load: Load) -> None:
            try:
                load.safe()
            except (DeviceError, OSError) as exc:
                problems.append(f"load {name} did not go safe: {exc}")

        # the loads go off beside the coil ramp: a supply that does not answer must not delay them
        threads = [timebase.Thread(load_off, args=item, name=f"safe-{item[0]}")
                   for item in self.loads.items()]  # fmt: skip
        for t in threads:
            t.start()
        if self.controller is not None:
            problems += [
                f"cage did not go fully safe: {p}" for p in self.controller.safe(relays=False)
            ]
        for t in threads:
            t.join(SAFE_TIMEOUT_S)
        if self.controller is not None:
            problems += [
                f"cage did not go fully safe: {p}" for p in self.controller.relays_normal()
            ]
        for p in problems:
            self.on_unsafe(p)
        return problems
