"""Execute a procedure on the rig: schedule commands, sample, record, analyse, safe state on exit.

Every exit path - success, a failed check, an error, a device that stops answering, Ctrl-C,
SIGTERM - leaves the ``with ExitStack()`` block, whose callbacks ramp the coils down and switch
every supply and load off before the links close; the run is then closed with its status.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import signal
import socket
import sys
import threading
import time
from array import array
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

import numpy as np

from drivers.errors import DeviceError
from drivers.protocols import Load
from rig import __version__
from rig.analysis import apply_correction
from rig.config import RigConfig
from rig.devices import thermometer_names
from rig.engine.cpu_wait import CpuWaitLog
from rig.engine.interlock import RigLock
from rig.engine.live import LiveView
from rig.engine.live_state import LivePublisher
from rig.engine.sampling import BufferedSensor, SensorSampler
from rig.engine.session import RigSession
from rig.engine.temperature_log import TemperatureLog
from rig.errors import RigError, RunAborted
from rig.lab.url import resolve_url
from rig.output_limits import refuse_cage_devices_as_loads
from rig.procedure.language import Procedure
from rig.procedure.plan import StepPlan, compile_plan, rig_timing, step_duration
from rig.steps import KINDS
from rig.steps.base import ChangeListener
from rig.store.run_control import run_page_url
from rig.store.run_store import RunReader, RunWriter, new_run

Confirm = Callable[[str], bool]
MONITOR_PERIOD_S = 0.2
STALL_S = 1.5
"""A sensor that sends nothing for this long (or 5 of its periods) has stalled."""
OWN_STALL_S = 0.3
"""The monitor woke this much later than its period: our own process was descheduled."""
COIL_CHECK_S = 1.0
"""How often the coil supplies' protection flags are read."""
CATCH_UP_S = 2.0
"""Longest wait at the end of a step for each sensor's samples up to that moment (s): they may sit
in a buffer while a busy computer runs something else (a null step's noise floor was once judged
on 3 of its 14 samples)."""
UNREAD_FAULT_AFTER = 2
"""Read-backs of an output that failed in a row (each after the link's own retries) before the
output counts as lost: one can be a glitch, two mean its state is unknown (a fault)."""
LAB_TIMEOUT_S = 5.0
"""Longest wait for the lab index at run close (s); then the run is synced later."""


@dataclass
class RunOutcome:
    """How a run ended."""

    status: str  # complete, failed (checks failed), aborted, error
    reason: str
    folder: Path
    results: dict[str, Any] = field(default_factory=dict)
    outputs: str = ""
    """What became of the outputs at the end, one line (empty: none was ever opened)."""

    @property
    def exit_code(self) -> int:
        """0 complete, 1 checks failed, 2 error, 130 aborted."""
        return {"complete": 0, "failed": 1, "error": 2, "aborted": 130}.get(self.status, 2)


class Runner:
    """Runs one procedure on one rig."""

    def __init__(self, proc: Procedure, cfg: RigConfig, runs_dir: Path, *, i2c_bus: Any | None = None,
                 confirm: Confirm | None = None, quiet: bool = False, live: bool = True,
                 guardian: bool = True, page_url: str | None = None) -> None:  # fmt: skip
        self.proc = proc
        self.cfg = cfg
        self.runs_dir = runs_dir
        self.i2c_bus = i2c_bus
        self.confirm = confirm
        self.quiet = quiet
        self.live_enabled = live and not quiet
        self.use_guardian = guardian
        self.results: dict[str, Any] = {}
        self.paused = threading.Event()
        self.abort = threading.Event()
        self.lateness_s = array("d")  # 8 bytes per command: a 10 h run at 50 Hz keeps 14 MB
        self.writer: RunWriter | None = None
        self.loads: dict[str, Load] = {}
        self.commanded_loads: dict[str, float] = {}
        self._load_change: dict[str, tuple[float, float]] = {}  # last change: (start, end) s
        self.measured_loads: dict[str, tuple[float, float]] = {}  # name -> (time, A)
        self.change_listeners: list[ChangeListener] = []
        self.status_sources: list[Callable[[], str]] = []
        self.live_sources: list[Callable[[], dict[str, Any]]] = []  # structured, for the page
        self.publisher: LivePublisher | None = None
        self.page_url = page_url  # the web page serving this run (rig run --serve), if any
        self.abort_reason: str | None = None
        self.holding = False  # paused and holding the schedule (a pause is asked by ``paused``)
        self.correction: dict[str, Any] | None = None
        self.lab_url: str | None = None  # the lab index to push the closed run to
        self.report_requested = False
        self.rig: RigSession | None = None
        self.unsafe: list[str] = []  # outputs that may still be on after the safe path
        self._unread: dict[str, int] = {}  # output -> read-backs failed in a row
        self._cpu_wait = CpuWaitLog()  # our threads' waits for a CPU, noted every health round
        self._coil_checked = 0.0
        self.samplers: dict[str, SensorSampler] = {}
        self.controller: Any = None
        self.live: LiveView | None = None
        self._timeline: list[tuple[str, float]] | None = None

    # --- lifecycle ------------------------------------------------------------------------------

    def run(self) -> RunOutcome:
        """Execute the whole procedure; always returns an outcome with the run folder."""
        params = self.proc.parameters
        # a password in [lab] url is refused before the configuration is copied into a run folder
        self.lab_url = resolve_url(None, self.cfg.raw, self.cfg.path)
        # a cage device named as a load: refused before anything is locked or switched on
        refuse_cage_devices_as_loads(list(self.proc.loads), self.cfg, self.proc.path)
        # The interlock first: a run refused because the rig is busy leaves no run folder.
        self._lock = RigLock(self.cfg, f"rig run {self.proc.path.name}")
        self._lock.acquire()
        self.writer = w = new_run(
            self.runs_dir, params.get("dut_serial") or self.proc.path.stem,
            procedure=self.proc.title, procedure_file=self.proc.path.name, parameters=params,
            operator=params.get("operator", ""), dut_serial=params.get("dut_serial", ""),
            software_version=__version__, rig_config=str(self.cfg.path), host=socket.gethostname(), magnetometers=self.proc.magnetometers,
            loads=list(self.proc.loads),
        )  # fmt: skip
        (w.folder / "procedure.yaml").write_text(self.proc.text, encoding="utf-8")
        shutil.copy(self.cfg.path, w.folder / "rig.toml")
        self.publisher = LivePublisher(self, self.timeline())
        self.publisher.start()
        if self.page_url is not None:
            print(f"rig: this run's page: {run_page_url(self.page_url, w.folder.name)}",
                  file=sys.stderr, flush=True)  # fmt: skip
        old = self._install_signals()
        status, reason = "error", "unknown"
        try:
            with ExitStack() as stack:
                try:
                    self._open(stack)
                    for plan in compile_plan(self.proc, rig_timing(self.cfg)):
                        self._execute(plan)
                except BaseException:
                    # when the run learnt of its end, before the safe path runs (fault matrix)
                    seen = self.rig.fault_at if self.rig is not None else None
                    w.set_meta(t_end_detected=seen or time.monotonic())
                    raise
            verdict = self.results.get("verdict", {}).get("overall")
            status, reason = (
                ("failed", "acceptance checks failed")
                if verdict == "FAIL"
                else ("complete", "all steps done")
            )
        except (KeyboardInterrupt, RunAborted) as exc:
            status, reason = (
                "aborted",
                self.abort_reason or str(exc) or "interrupted by the operator (Ctrl-C)",
            )
        except (RigError, DeviceError) as exc:
            status, reason = "error", str(exc)
        except Exception as exc:  # record it, leave hardware safe (done above), then re-raise
            status, reason = "error", f"internal error: {type(exc).__name__}: {exc}"
            raise
        finally:
            if self.live is not None:
                self.live.stop()
            outputs = self._outputs_note()
            if outputs:
                self._event("error" if self.unsafe else "info", outputs)
            for name, s in self.samplers.items():
                w.set_meta(**{f"samples_{name}": s.count, f"retried_{name}": s.retried})
            if self.lateness_s:
                lat = np.frombuffer(self.lateness_s, dtype=float)
                w.set_meta(command_lateness_p50_ms=float(1000 * np.percentile(lat, 50)),
                           command_lateness_p99_ms=float(1000 * np.percentile(lat, 99)),
                           command_lateness_max_ms=float(1000 * lat.max()),
                           commands_scheduled=int(lat.size))  # fmt: skip
            for problem in w.close(status, reason):
                print(
                    f"rig: WARNING: {problem}; the data committed before it is kept",
                    file=sys.stderr,
                )
            self._lock.release()  # the session released it already, unless it never opened
            self._restore_signals(old)
            self.publisher.stop(status, reason)
        # a report asked for while the run was recording says RUNNING: rebuilt now it is closed
        stale = any((w.folder / n).exists() for n in ("report.html", "report.txt", "report.pdf"))
        if self.report_requested or stale:
            self._write_report(w.folder)
        if self.lab_url is not None:
            self._sync_lab(self.lab_url, w.folder)
        return RunOutcome(status, reason, w.folder, self.results, outputs)

    def _outputs_note(self) -> str:
        """One line on the outputs after the session's safe path ('' if none was opened)."""
        if self.rig is None:
            return ""
        if self.unsafe:
            return (f"outputs: {len(self.unsafe)} may still be on ({self.unsafe[0]}); switch them"
                    f" off by hand or with 'rig safe --rig {self.cfg.path}'")  # fmt: skip
        return (
            "outputs: safe - coils ramped down and off, every supply and load off, polarity"
            " relays normal"
        )

    def _sync_lab(self, url: str, folder: Path) -> None:
        """Push the closed run to the lab index; best effort: a failure is one warning line and
        the run stays as recorded ('rig lab sync' pushes it later)."""
        from rig.lab.sync import sync_runs
        from rig.lab.url import masked

        try:
            report = sync_runs(url, [folder], timeout_s=LAB_TIMEOUT_S)
            if report.added and not self.quiet:
                print(f"rig: run added to the lab index {masked(url)}", file=sys.stderr)
            for why in report.refused + report.not_stored + report.unreadable:
                print(f"rig: WARNING: the lab index did not take this run: {why}", file=sys.stderr)
        except Exception as exc:  # never a failed run: the folder is the record
            print(f"rig: WARNING: the run was not added to the lab index ({masked(str(exc))});"
                  " 'rig lab sync' adds it later", file=sys.stderr)  # fmt: skip

    def _write_report(self, folder: Path) -> None:
        """The acceptance report of the closed run; a failure leaves the run as recorded."""
        from rig.report.acceptance import build_report

        if not self.quiet:
            print("rig: writing the report ...", file=sys.stderr)
        try:
            build_report(folder)
        except Exception as exc:  # the run and its data stand; the report can be rebuilt
            print(f"rig: WARNING: the report could not be written ({type(exc).__name__}: {exc});"
                  f" rebuild it with 'rig report {folder}'", file=sys.stderr)  # fmt: skip

    def _install_signals(self) -> dict[int, Any]:
        if threading.current_thread() is not threading.main_thread():
            return {}

        def on_term(signum: int, frame: FrameType | None) -> None:
            raise RunAborted(f"stopped by {signal.Signals(signum).name}")

        def on_usr1(signum: int, frame: FrameType | None) -> None:
            if self.paused.is_set():
                self.paused.clear()
            else:
                self.paused.set()

        return {
            signal.SIGTERM: signal.signal(signal.SIGTERM, on_term),
            signal.SIGHUP: signal.signal(signal.SIGHUP, on_term),  # the terminal went away
            signal.SIGUSR1: signal.signal(signal.SIGUSR1, on_usr1),
        }

    @staticmethod
    def _restore_signals(old: dict[int, Any]) -> None:
        for s, h in old.items():
            signal.signal(s, h)

    def _event(self, level: str, message: str) -> None:
        assert self.writer is not None
        t = time.monotonic()
        self.writer.add_event(t, level, message)
        if self.publisher is not None:
            self.publisher.note_event(t, level, message)

    def timeline(self) -> list[tuple[str, float]]:
        """Every step's name and nominal duration (s), worked out once without compiling the
        steps' commands (an orbit replay's take a quarter of a second)."""
        if self._timeline is None:
            timing = rig_timing(self.cfg)
            self._timeline = [(step.name, step_duration(step, timing)) for step in self.proc.steps]
        return self._timeline

    def abort_from(self, reason: str) -> None:
        """Abort the run through the safe path (as Ctrl-C does), recording ``reason``."""
        if self.abort_reason is None:
            self.abort_reason = reason
        self.abort.set()

    def corrected_dut(self, raw_ut: Any) -> Any:
        """The DUT reading ``raw_ut`` (uT) corrected by the newest calibration this run has
        fitted (loads at their commanded currents), None before the first one."""
        if raw_ut is None:
            return None
        for value in reversed(list(self.results.values())):
            corr = value.get("correction") if isinstance(value, dict) else None
            if isinstance(corr, dict) and "matrix" in corr:
                channels = list(corr.get("k_ut_per_unit", {}))
                loads = np.array([[self.commanded_loads.get(ch, 0.0) for ch in channels]])
                return apply_correction(corr, np.asarray(raw_ut, float)[None, :], loads,
                                        channels)[0]  # fmt: skip
        return None

    def _open(self, stack: ExitStack) -> None:
        """Open every device; register safe states and closes on ``stack`` (LIFO)."""
        w = self.writer
        assert w is not None
        self.rig = rig = stack.enter_context(
            RigSession(
                self.cfg,
                command=self._lock.command,
                folder=w.folder,
                guardian=self.use_guardian,
                lock=self._lock,
                i2c_bus=self.i2c_bus,
                abort=self.abort,
                on_unsafe=self._unsafe,
            )
        )
        self.controller = rig.cage()
        instruments = dict(self.controller.instruments())
        mags = self.proc.magnetometers
        for role, dev_name in mags.items():
            if dev_name not in self.cfg.devices:
                raise RigError(
                    f"{self.proc.path}: magnetometer role '{role}' names '{dev_name}',"
                    f" which is not in {self.cfg.path}"
                )
        cage_reference = self.cfg.cage.reference if self.cfg.cage is not None else None
        for dev_name in dict.fromkeys(mags.values()):  # one sampler per device, whatever its roles
            driver = rig.magnetometer(dev_name)
            with contextlib.suppress(Exception):  # an identity is for the record only
                ident = driver.identify()
                instruments[dev_name] = f"{ident.model} {ident.serial}".strip()
            rate = float(self.cfg.devices[dev_name].get("rate_hz", 20.0))
            sampler = SensorSampler(dev_name, driver, w.add_sample, rate,
                                    on_warning=lambda m: self._event("warning", m))  # fmt: skip
            sampler.start()
            stack.callback(sampler.stop)
            self.samplers[dev_name] = sampler
            if dev_name == cage_reference:
                self.controller.reference = BufferedSensor(sampler)
        for name in self.proc.loads:
            if name not in self.cfg.devices:
                raise RigError(
                    f"{self.proc.path}: load '{name}' is not a device in {self.cfg.path}"
                )
            load = rig.load(name)  # at 0 A, output on; off when the session ends
            self.loads[name] = load
            self.commanded_loads[name] = 0.0
            with contextlib.suppress(Exception):
                ident = load.identify()
                instruments[name] = f"{ident.model} {ident.serial}".strip()
        thermometers = self._record_thermometers(stack, instruments)
        for step in self.proc.steps:
            for name in KINDS[step.kind].thermometers(step):
                if name not in thermometers:
                    raise RigError(
                        f"{self.proc.path}: step '{step.name}' reads thermometer '{name}', which"
                        f" this run does not record (recording: {', '.join(thermometers) or 'none'});"
                        f" add it to {self.cfg.path} or fix the name"
                    )
        correction = None
        ref_name = mags.get("reference")
        if (
            ref_name
            and ref_name in self.cfg.devices
            and self.cfg.devices[ref_name].get("correction_matrix") is not None
        ):
            dev = self.cfg.devices[ref_name]
            correction = {
                "matrix": dev.get("correction_matrix"),
                "offset_ut": dev.get("correction_offset_ut", [0, 0, 0]),
            }
        w.set_meta(instruments=instruments, reference_correction=correction,
                   cage_model=self.controller.model.to_dict(),
                   thermometers=thermometers)  # fmt: skip
        self.correction = correction
        monitor_stop = threading.Event()
        monitor = threading.Thread(
            target=self._monitor, args=(monitor_stop,), name="current-monitor", daemon=True
        )
        monitor.start()
        stack.callback(monitor.join, 2.0)
        stack.callback(monitor_stop.set)
        if self.live_enabled:
            self.live = LiveView(self)
            self.live.start()
        # Registered last so it runs first on the way out: the coils are ramped down and every
        # output switched off before anything else is stopped (safe() is idempotent).
        stack.callback(rig.safe)

    def _record_thermometers(self, stack: ExitStack, instruments: dict[str, str]) -> list[str]:
        """Start recording every thermometer of the rig (channels in degrees C, one reading a
        second); one that cannot be opened is a warning, never the end of the run. Returns the
        names being recorded."""
        assert self.rig is not None and self.writer is not None
        recorded = []
        for name in thermometer_names(self.cfg):
            try:
                thermometer = self.rig.thermometer(name)
                with contextlib.suppress(Exception):  # an identity is for the record only
                    ident = thermometer.identify()
                    instruments[name] = f"{ident.model} {ident.serial}".strip()
            except (DeviceError, OSError, RigError) as exc:
                self._event("warning", f"{exc}; the run goes on without recording {name}")
                continue
            log = TemperatureLog(name, thermometer, self.writer.add_channel, self._event)
            log.start()
            stack.callback(log.stop)
            recorded.append(name)
        return recorded

    def _unsafe(self, message: str) -> None:
        """An output that may still be on: recorded, and told to the operator whatever -q says."""
        self.unsafe.append(message)
        self._event("error", message)
        print(f"rig: WARNING: {message}; switch it off by hand", file=sys.stderr)

    def _monitor(self, stop: threading.Event) -> None:
        """Read back load currents and watch the rig's health at about 5 Hz: a tripped supply, a
        stalled or frozen sensor or a store that cannot write ends the run (see ``fault``). If
        the watching itself fails, nothing watches the run any more: that is a fault too."""
        try:
            self._watch(stop)
        except Exception as exc:  # a monitor that died silently would leave the run unwatched
            self._fail(f"the health monitor stopped ({type(exc).__name__}: {exc}); the run is"
                       " no longer watched, so it ends here: report this")  # fmt: skip

    def _watch(self, stop: threading.Event) -> None:
        """The monitor's loop (:meth:`_monitor`)."""
        w = self.writer
        assert w is not None
        last = time.monotonic()
        while not stop.wait(MONITOR_PERIOD_S):
            now = time.monotonic()
            # This thread woke late: the whole process was descheduled (a busy computer). The
            # samplers were too and need a moment to hand over what their sensors sent meanwhile,
            # so their freshness is judged on the next round, not now.
            own_stall = now - last > MONITOR_PERIOD_S + OWN_STALL_S
            for name, load in list(self.loads.items()):
                try:
                    # On a slow link a read can overlap a change of the same channel (seen: 2.5 A
                    # read back 40 ms after the 0 A command, taken as the current for 0.5 s):
                    # such a reading is dropped; any other holds from when it was asked.
                    t_asked = time.monotonic()
                    reading = load.read()
                    started, ended = self._load_change.get(name, (math.inf, math.inf))
                    if started <= time.monotonic() and ended >= t_asked:
                        continue  # the current changed while it was read: which one is it?
                    self.measured_loads[name] = (t_asked, float(reading.i_out_a))
                    w.add_channel(
                        t_asked, name, self.commanded_loads.get(name), float(reading.i_out_a)
                    )
                    if reading.protection:
                        self._fail(f"{name}: the output tripped ({reading.protection}) and is off;"
                                   " check the wiring and the load before running again")  # fmt: skip
                    self._unread.pop(name, None)
                except (DeviceError, OSError) as exc:
                    self._not_answering(name, exc)
            self._check_health(w, judge_sensors=not own_stall)
            # only the wait is judged for oversleeping: slow load read-backs (a busy bus, long
            # retries) must not count as this process being descheduled, or a frozen sensor
            # would never be judged (a stuck DUT ran on for 27 s under a CPU hog)
            last = time.monotonic()

    def _check_health(self, w: RunWriter, judge_sensors: bool = True) -> None:
        if w.error is not None:
            self._fail(f"cannot write the run data ({w.error}): is the disk full? Free space under"
                       f" {w.folder.parent}; what was recorded before is kept")  # fmt: skip
        now = time.monotonic()
        self._cpu_wait.note(now)
        for name, sampler in list(self.samplers.items()) if judge_sensors else []:
            stall_s = max(STALL_S, 5.0 / sampler.rate_hz)
            stuck_after = int(self.cfg.devices[name].get("stuck_after")) or 10**9  # 0: never
            problem = sampler.health(now, stall_s, stuck_after, self._cpu_wait)
            if problem is not None:
                self._fail(problem)
        ctl = self.controller
        if ctl is not None and ctl.enabled and self._coil_check_due(now):
            for axis, drive in enumerate(ctl.axes):
                t_asked = time.monotonic()  # as for the loads: the reading is from after this
                try:
                    reading = drive.supply.read()
                    self._unread.pop(f"coil_{'xyz'[axis]}", None)
                except (DeviceError, OSError) as exc:
                    self._not_answering(f"coil_{'xyz'[axis]}", exc)
                    continue
                protection = reading.protection
                # the supply reads an unsigned current; a polarity relay gives it its sign
                sign = 1 if drive.bipolar else ctl.signs[axis]
                w.add_channel(t_asked, f"coil_{'xyz'[axis]}", None, sign * float(reading.i_out_a))
                if protection:
                    self._fail(f"coil {'xyz'[axis]} supply tripped ({protection}) and is off;"
                               " check the coil wiring, then run again")  # fmt: skip

    def _not_answering(self, name: str, exc: Exception) -> None:
        """An output that did not answer a read-back (its link already retried): a warning the
        first time; UNREAD_FAULT_AFTER times in a row, a fault (its state is no longer known)."""
        self._unread[name] = self._unread.get(name, 0) + 1
        if self._unread[name] >= UNREAD_FAULT_AFTER:
            self._fail(f"{exc}; {name} stopped answering, so its output is not under control")
        else:
            self._event("warning", f"reading {name}: {exc}")

    def _coil_check_due(self, now: float) -> bool:
        if now - self._coil_checked < COIL_CHECK_S:
            return False
        self._coil_checked = now
        return True

    @property
    def fault(self) -> str | None:
        """The first fault found by any thread (None: none so far)."""
        return None if self.rig is None else self.rig.fault

    def _fail(self, message: str) -> None:
        """A fault found off the main thread: the main thread raises it at its next wait."""
        assert self.rig is not None
        self.rig.fail(message)

    # --- steps ----------------------------------------------------------------------------------

    def _wait_until(self, t_target: float, stop: threading.Event | None = None) -> float:
        """Sleep until ``t_target`` (monotonic) or until ``stop`` is set, honouring pause and
        abort; returns the time shift added by pauses."""
        assert self.rig is not None
        shift = 0.0
        while True:
            self.rig.check()  # a fault or an abort ends the wait
            if stop is not None and stop.is_set():
                return shift
            if self.paused.is_set():
                t_pause = time.monotonic()
                self._event("operator", "paused")
                self.holding = True
                try:
                    while self.paused.is_set() and not self.abort.is_set():
                        self.rig.sleep(0.05)
                finally:
                    self.holding = False
                shift += time.monotonic() - t_pause
                self._event("operator", "resumed")
                continue
            remaining = t_target + shift - time.monotonic()
            if remaining <= 0:
                return shift
            time.sleep(min(remaining, 0.05))

    def _execute(self, plan: StepPlan) -> None:
        """Carry out one step: its field and load set-points on time, its own action through its
        kind (rig.steps), which also decides what happens before and after."""
        w = self.writer
        assert w is not None
        step = plan.step
        kind = KINDS[step.kind]
        t0 = time.monotonic()
        self.current_step = (step.index, step.name, t0, plan.duration_s)
        w.set_step(step.index, step.name, step.kind, t0, None)
        self._event("info", f"step {step.index + 1}/{len(self.proc.steps)}: {step.name}")
        execution = kind.execution(self, step)
        stop = execution.stop
        try:
            for cmd in plan.commands:
                t0 += self._wait_until(t0 + cmd.t_s, stop)
                if stop is not None and stop.is_set():
                    break
                now = time.monotonic()
                if cmd.kind in ("field", "load"):
                    self.lateness_s.append(now - (t0 + cmd.t_s))
                    self.command(step.index, cmd.kind, cmd.payload, now)
                    if cmd.kind == "field" and kind.hold_from_field:
                        t0 = time.monotonic() - cmd.t_s  # its dwell starts once the field is there
                elif cmd.kind != "end":
                    execution.run(cmd.payload)
            execution.wind_down()
        except BaseException:
            execution.abort()
            raise
        t_end = time.monotonic()
        w.set_step(step.index, step.name, step.kind, self.current_step[2], t_end)
        # the step's data are all in before it is judged
        for sampler in list(self.samplers.values()):
            sampler.caught_up(t_end, CATCH_UP_S)
        execution.finish(self.current_step[2], t_end)

    # --- what a step may use (rig.steps.base.RunContext) ------------------------------------------

    @property
    def folder(self) -> Path:
        """The run folder."""
        assert self.writer is not None
        return self.writer.folder

    def event(self, level: str, message: str) -> None:
        """Record an event (info, warning, error, operator)."""
        self._event(level, message)

    def record_result(self, name: str, value: Any) -> None:
        """Keep a result for later steps and store it."""
        assert self.writer is not None
        self.results[name] = value
        self.writer.set_result(name, value)

    def open_reader(self) -> RunReader:
        """The store as recorded so far (flushed first); the caller closes it."""
        assert self.writer is not None
        self.writer.flush()
        return RunReader(self.writer.folder)

    def set_meta(self, **values: Any) -> None:
        """Store run metadata."""
        assert self.writer is not None
        self.writer.set_meta(**values)

    def ask_operator(self, text: str) -> bool:
        """A yes/no question, answered by ``confirm`` (``--yes``, tests), or on the web page or
        the terminal, whichever answers first. Without a terminal the page alone can answer."""
        assert self.rig is not None and self.publisher is not None
        with self.rig.waiting_for_operator():  # as long as the operator takes: not a hang
            if self.confirm is not None:
                return self.confirm(text)
            prompt = self.publisher.open_prompt(text)
            self._event("operator", f"asked: {text}")
            try:
                answer = self._first_answer(prompt, text)
            finally:
                self.publisher.close_prompt()
            return answer

    def _first_answer(self, prompt: int, text: str) -> bool:
        assert self.rig is not None and self.publisher is not None
        terminal = _terminal_answers() if sys.stdin.isatty() else None
        if terminal is not None:
            terminal.ask(f"\n{text} [y/N] ")
        elif self.page_url is None:
            raise RigError(f"the procedure asks the operator: {text!r}; run in a terminal,"
                           " answer it on the page ('rig run --serve'), or pass --yes")  # fmt: skip
        while True:
            self.rig.check()  # an abort (page, signal) ends the question too
            page = self.publisher.wait_answer(prompt, 0.1)
            if page is not None:
                if terminal is not None:
                    print("(answered on the web page)", file=sys.stderr)
                return page
            if terminal is not None:
                line = terminal.answer()
                if line is not None:
                    return line.strip().lower() in ("y", "yes")

    def request_report(self) -> None:
        """Write the acceptance report once the run is closed and sealed."""
        self.report_requested = True

    def command(self, step_idx: int, kind: str, payload: dict[str, Any], now: float) -> None:
        """Carry out a ``field`` or ``load`` command; change listeners (a live calibration) are
        told when it starts and ends."""
        listeners = list(self.change_listeners)
        for listener in listeners:
            listener.change_started(now)
        try:
            if kind == "field":
                self._set_field(step_idx, payload, now)
            elif kind == "load":
                self._set_load(step_idx, payload, now)
            else:
                raise AssertionError(kind)
        finally:
            for listener in listeners:
                listener.change_ended(time.monotonic())

    def _set_field(self, step_idx: int, payload: dict[str, Any], now: float) -> None:
        w = self.writer
        assert w is not None
        target = np.array(payload["field_ut"])
        issued = now
        if payload.get("track"):
            # One tracked set-point moves the field by a slew-limited step that the reference
            # follows (interpolated): no interval to leave out. A ramp through zero is one.
            ramped = self.controller.track(target)
            payload = payload | {"ramped": ramped}
            if not ramped:
                issued = time.monotonic()
        elif payload.get("trim"):
            result = self.controller.trim(target)
            if not result.settled:
                self._event("warning", f"trim did not settle: {result.error_nt:.1f} nT")
        else:
            self.controller.set_field(target)
        # Logged when the ramp has finished: analysis counts settling from here.
        done = time.monotonic()
        w.add_command(done, step_idx, "field", payload | {"t_issued": min(issued, done)})
        for ax, amps in enumerate(self.controller.currents):
            w.add_channel(time.monotonic(), f"coil_{'xyz'[ax]}", float(amps), None)

    def _set_load(self, step_idx: int, payload: dict[str, Any], now: float) -> None:
        w = self.writer
        assert w is not None
        name, amps = payload["channel"], float(payload["current_a"])
        self._load_change[name] = (now, math.inf)
        try:
            self.loads[name].set_current(amps)
        finally:
            done = time.monotonic()  # logged once written, like a field: settling counts from here
            self._load_change[name] = (now, done)
        self.commanded_loads[name] = amps
        w.add_command(done, step_idx, "load", payload | {"t_issued": min(now, done)})
        w.add_channel(done, name, amps, None)


class _TerminalAnswers:
    """Lines typed on the terminal, read by one thread for the whole process: a question answered
    on the page leaves no reader behind to steal the next answer (stale lines are dropped)."""

    def __init__(self) -> None:
        import queue

        self.lines: queue.Queue[str] = queue.Queue()
        self._thread = threading.Thread(target=self._read, name="terminal-answers", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for line in sys.stdin:
            self.lines.put(line)

    def ask(self, question: str) -> None:
        """Drop what was typed before and show ``question``."""
        import queue

        while True:
            try:
                self.lines.get_nowait()
            except queue.Empty:
                break
        print(question, end="", file=sys.stderr, flush=True)

    def answer(self) -> str | None:
        """A line typed since :meth:`ask`, or None."""
        import queue

        try:
            return self.lines.get_nowait()
        except queue.Empty:
            return None


_TERMINAL: list[_TerminalAnswers] = []


def _terminal_answers() -> _TerminalAnswers:
    if not _TERMINAL:
        _TERMINAL.append(_TerminalAnswers())
    return _TERMINAL[0]
