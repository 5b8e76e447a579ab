"""Execute a procedure on the rig: the run from its lock to its sealed folder, and the
``RunContext`` its steps use. The parts, one job each (ADR 0023):

* :mod:`rig.engine.recording` opens and closes the run folder, then the report and the lab index;
* :mod:`rig.engine.session` (``RigSession``) owns the interlock, the guardian and the safe state of
  every output on every exit path (ADR 0012), and nothing else registers it;
* :mod:`rig.engine.run_devices` opens the run's devices inside the session;
* :mod:`rig.engine.health` watches the run from a thread of its own;
* :mod:`rig.engine.schedule` and :mod:`rig.engine.commands` carry out each step on time;
* :mod:`rig.engine.operator_channel` asks the operator and takes the signals;
* :mod:`rig.engine.run_tracker` holds the run's state (the table of :mod:`rig.store.run_states`),
  the pause and abort requests and the step under way, which the live view and the page read.
"""

from __future__ import annotations

import sys
from array import array
from collections.abc import Callable, Mapping
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import timebase
from drivers.errors import DeviceError
from rig import host_identity
from rig.config import RigConfig
from rig.engine.commands import Commands, LoadBook
from rig.engine.field_guard import guard_the_field
from rig.engine.health import HealthMonitor, closed_by_other_line
from rig.engine.interlock import RigLock
from rig.engine.operator_channel import Confirm, OperatorChannel, install_signals, restore_signals
from rig.engine.page_feed import LivePublisher
from rig.engine.recording import (
    LAB_TIMEOUT_S as LAB_TIMEOUT_S,
)
from rig.engine.recording import (
    close_record,
    note_closed_by_other,
    open_record,
    outputs_note,
    sync_lab,
    write_report,
)
from rig.engine.run_devices import (
    check_thermometers,
    open_loads,
    record_thermometers,
    reference_correction,
    start_samplers,
    warn_expired_certificates,
)
from rig.engine.run_tracker import RunTracker
from rig.engine.sampling import SensorSampler
from rig.engine.schedule import StepScheduler
from rig.engine.session import RigSession
from rig.engine.terminal_view import LiveView
from rig.errors import RigError, RunAborted
from rig.lab.url import resolve_url
from rig.procedure.language import Procedure
from rig.procedure.plan import compile_plan, rig_timing, step_duration
from rig.procedure.preflight import refuse_what_check_refuses
from rig.steps.base import ChangeListener
from rig.steps.vocabulary import FieldCommand, LoadCommand, Step
from rig.store.run_control import run_page_url
from rig.store.run_states import EXIT_CODES, RunStatus, Verdict
from rig.store.run_store import RunReader, RunWriter
from rig.stored import JsonObject, JsonValue
from rig.verdict import check_verdict

if TYPE_CHECKING:
    from drivers.protocols import ScalarMagnetometer
    from rig.cage.controller import CageController
    from rig.calibration.forecast import SigmaForecast


@dataclass
class RunOutcome:
    """How a run ended."""

    status: RunStatus
    reason: str
    folder: Path
    results: dict[str, JsonObject] = field(default_factory=dict)
    outputs: str = ""
    """What became of the outputs at the end, one line (empty: none was ever opened)."""

    @property
    def exit_code(self) -> int:
        """0 complete, 1 checks failed, 2 error, 130 aborted."""
        return EXIT_CODES.get(self.status, 2)


class Runner:
    """Runs one procedure on one rig."""

    def __init__(self, proc: Procedure, cfg: RigConfig, runs_dir: Path, *, i2c_bus: Any | None = None,
                 confirm: Confirm | None = None, quiet: bool = False, live: bool = True,
                 guardian: bool = True, page_url: str | None = None) -> None:  # fmt: skip
        self.proc = proc
        self.cfg = cfg
        self.runs_dir = runs_dir
        self.i2c_bus = i2c_bus
        self.quiet = quiet
        self.live_enabled = live and not quiet
        self.use_guardian = guardian
        self.page_url = page_url  # the web page serving this run (rig run --serve), if any
        self.tracker = RunTracker()
        self.operator = OperatorChannel(confirm, page_url, self._event)
        self.results: dict[str, JsonObject] = {}
        self.loads = LoadBook()
        self.commanded_loads = self.loads.commanded
        self.measured_loads = self.loads.measured
        self.change_listeners: list[ChangeListener] = []
        self.status_sources: list[Callable[[], str]] = []  # a short text each, for the terminal
        self.live_sources: list[Callable[[], JsonObject]] = []  # the page's values from steps
        self.samplers: dict[str, SensorSampler] = {}
        self.cage_controller: CageController | None = None  # once the devices are open
        self.correction: dict[str, Any] | None = None
        self.writer: RunWriter | None = None
        self.rig: RigSession | None = None  # the session, once its devices are open
        self.session: RigSession | None = None  # the session, once made (entered or not)
        self.publisher: LivePublisher | None = None
        self.live: LiveView | None = None
        self.scheduler: StepScheduler | None = None
        self.commands: Commands | None = None
        self.lab_url: str | None = None  # the lab index to push the closed run to
        self.report_requested = False
        self.unsafe: list[str] = []  # outputs that may still be on after the safe path
        self._timeline: list[tuple[str, float]] | None = None

    # --- lifecycle ------------------------------------------------------------------------------

    def run(self) -> RunOutcome:
        """Execute the whole procedure; always returns an outcome with the run folder."""
        # a password in [lab] url is refused before the configuration is copied into a run folder
        self.lab_url = resolve_url(None, self.cfg.raw, self.cfg.path)
        # whatever rig check --rig refuses (one instrument under two names, a cage device as a
        # load, a field, current or load beyond a limit, a sine beyond the cage's bandwidth):
        # refused before anything is locked, recorded or switched on
        refuse_what_check_refuses(self.proc, self.cfg)
        # The interlock first: a run refused because the rig is busy leaves no run folder.
        self._lock = RigLock(self.cfg, f"rig run {self.proc.path.name}")
        self._lock.acquire()
        self.writer = w = open_record(self.runs_dir, self.proc, self.cfg)
        self.commands = Commands(w, self.loads, self.change_listeners, self._event)
        self.publisher = LivePublisher(self, self.timeline())
        self.publisher.start()
        if self.page_url is not None:
            print(f"rig: this run's page: {run_page_url(self.page_url, w.folder.name)}",
                  file=sys.stderr, flush=True)  # fmt: skip
        old = install_signals(self.tracker)
        status, reason = RunStatus.ERROR, "unknown"
        try:
            self._carry_out(w)
            status, reason = self._ended_status()
        except (KeyboardInterrupt, RunAborted) as exc:
            status = RunStatus.ABORTED
            reason = self.tracker.abort_reason or str(exc) or "interrupted by the operator (Ctrl-C)"
        except (RigError, DeviceError) as exc:
            status, reason = RunStatus.ERROR, str(exc)
        except Exception as exc:  # record it, leave hardware safe (done above), then re-raise
            status, reason = RunStatus.ERROR, f"internal error: {type(exc).__name__}: {exc}"
            raise
        finally:
            outputs, status, reason = self._close(w, status, reason, old)
        if w.closed_by_other is None:
            self._after_close(w.folder)
        # else: the run is the other process's record now; no report, no lab index (ADR 0036)
        return RunOutcome(status, reason, w.folder, self.results, outputs)

    def _carry_out(self, w: RunWriter) -> None:
        """Open the session and the devices, then every step; the session takes every output to
        its safe state on the way out, whatever the way."""
        with ExitStack() as stack:
            try:
                rig = stack.enter_context(self._session(w))
                self._open(rig, w)
                for plan in compile_plan(self.proc, rig_timing(self.cfg)):
                    assert self.scheduler is not None
                    self.scheduler.execute(plan, self)
            except BaseException:
                # when the run learnt of its end, before the safe path runs (fault matrix)
                seen = self.rig.fault_at if self.rig is not None else None
                w.set_meta(t_end_detected=seen or timebase.monotonic())
                raise

    def _ended_status(self) -> tuple[RunStatus, str]:
        """Every step done: re-run if the data a check judged failed the timing checks, failed
        if an acceptance check failed, else complete."""
        verdict = check_verdict(self.results)
        overall = verdict.overall if verdict is not None else None
        if verdict is not None and overall == Verdict.RERUN:
            steps = ", ".join(result for result, _ in verdict.rerun)
            return RunStatus.RERUN, (f"not judged: the data of {steps} failed the timing checks;"
                                     " run the procedure again on a less busy computer")  # fmt: skip
        if overall == Verdict.FAIL:
            return RunStatus.FAILED, "acceptance checks failed"
        return RunStatus.COMPLETE, "all steps done"

    def _close(
        self, w: RunWriter, status: RunStatus, reason: str, old: dict[int, Any]
    ) -> tuple[str, RunStatus, str]:
        """The run to ``status``, recorded and closed, the lock and signals given back; returns
        the line on the outputs and the status and reason the run ended with: ``error`` and the
        one line of :func:`closed_by_other_line` when another process closed the run meanwhile
        (its status and seal are left as they are, the fact noted beside them, ADR 0036)."""
        if self.live is not None:
            self.live.stop()
        read_back = self.session.read_back if self.session is not None else None
        outputs = outputs_note(read_back, self.cfg.path)
        if outputs:
            still_on = read_back is not None and not all(s.off for s in read_back.values())
            self._event("error" if still_on else "info", outputs)
        lateness = self.scheduler.lateness_s if self.scheduler is not None else array("d")
        close_record(w, status, reason, self.samplers, lateness)
        if w.closed_by_other is not None:
            intended = f"{status}: {reason}"
            status, reason = RunStatus.ERROR, closed_by_other_line(w.closed_by_other)
            note_closed_by_other(w, reason, intended, outputs)
        self._lock.release()  # the session released it already, unless it never opened
        restore_signals(old)
        assert self.publisher is not None
        self.publisher.stop(status, reason)
        self.tracker.to(status)
        return outputs, status, reason

    def _after_close(self, folder: Path) -> None:
        """The report (asked for, or one written while the run was recording, which says
        RUNNING: rebuilt now it is closed), then the lab index."""
        stale = any((folder / n).exists() for n in ("report.html", "report.txt", "report.pdf"))
        if self.report_requested or stale:
            write_report(folder, self.quiet)
        if self.lab_url is not None:
            self._sync_lab(self.lab_url, folder)

    def _sync_lab(self, url: str, folder: Path) -> None:
        """Push the closed run to the lab index (best effort, :func:`recording.sync_lab`)."""
        sync_lab(url, folder, self.quiet)

    def _session(self, w: RunWriter) -> RigSession:
        self.session = RigSession(self.cfg, command=self._lock.command, folder=w.folder,
                                  guardian=self.use_guardian, lock=self._lock,
                                  i2c_bus=self.i2c_bus, abort=self.tracker.abort_requested,
                                  on_unsafe=self._unsafe, on_found_on=self._found_on)  # fmt: skip
        return self.session

    def _open(self, rig: RigSession, w: RunWriter) -> None:
        """Open every device through ``rig`` (entered), start the health monitor and the live
        view; everything started stops through the session, after its safe state."""
        self.rig = rig
        if rig.guardian is not None:  # a reader leaves the run to a live guardian to close
            w.set_meta(guardian=host_identity.identity(rig.guardian.proc.pid))
        elif rig.no_guardian is not None:  # simulated time: nothing to guard outside this process
            self._event("info", rig.no_guardian)
        assert self.commands is not None
        self.cage_controller = self.commands.controller = rig.cage()
        instruments = dict(self.cage_controller.instruments())
        start_samplers(rig, self.proc, self.cfg, w, self.samplers, instruments, self._event)
        guard_the_field(rig, self.cfg, self.samplers)  # the field limit on what is measured
        open_loads(rig, self.proc, self.cfg, self.loads, instruments, self._event)
        thermometers = record_thermometers(rig, self.cfg, w, instruments, self._event)
        check_thermometers(self.proc, self.cfg, thermometers)
        self.correction = reference_correction(self.proc, self.cfg)
        warn_expired_certificates(self.cfg, self._event)
        w.set_meta(instruments=instruments, reference_correction=self.correction,
                   cage_model=self.cage_controller.model.to_dict(),
                   thermometers=thermometers)  # fmt: skip
        self.scheduler = StepScheduler(rig, w, self.tracker, self.commands, self.samplers,
                                       len(self.proc.steps), self._event)  # fmt: skip
        monitor = HealthMonitor(rig, w, self.cfg, self.samplers, self.loads, self._event)
        monitor.start()
        rig.on_close(monitor.stop)
        if self.live_enabled:
            self.live = LiveView(self)
            self.live.start()

    def _unsafe(self, message: str) -> None:
        """An output that may still be on: recorded, and told to the operator whatever -q says."""
        self.unsafe.append(message)
        self._event("error", message)
        print(f"rig: WARNING: {message}; switch it off by hand", file=sys.stderr)

    def _found_on(self, message: str) -> None:
        """An output found on at the start and switched off: recorded, and told whatever -q says."""
        self._event("warning", message)
        print(f"rig: WARNING: {message}", file=sys.stderr)

    def _event(self, level: str, message: str) -> None:
        assert self.writer is not None
        t = timebase.monotonic()
        self.writer.add_event(t, level, message)
        if self.publisher is not None:
            self.publisher.note_event(t, level, message)

    # --- what the live view, the page and the fault lab read ----------------------------------

    def timeline(self) -> list[tuple[str, float]]:
        """Every step's name and nominal duration (s), worked out once without compiling the
        steps' commands (an orbit replay's take a quarter of a second)."""
        if self._timeline is None:
            timing = rig_timing(self.cfg)
            self._timeline = [(step.name, step_duration(step, timing)) for step in self.proc.steps]
        return self._timeline

    @property
    def current_step(self) -> tuple[int, str, float, float] | None:
        """(index, name, start, nominal duration) of the step under way; None before the first."""
        s = self.tracker.step
        return None if s is None else (s.index, s.name, s.t_start, s.duration_s)

    def abort_from(self, reason: str) -> None:
        """Abort the run through the safe path (as Ctrl-C does), recording ``reason``."""
        self.tracker.request_abort(reason)

    @property
    def controller(self) -> CageController:
        """The cage's controller (RigError before the devices are open: no step runs then)."""
        if self.cage_controller is None:
            raise RigError("the cage is not open yet: no step runs before the devices are")
        return self.cage_controller

    @property
    def fault(self) -> str | None:
        """The first fault found by any thread (None: none so far)."""
        return None if self.rig is None else self.rig.fault

    # --- what a step may use (rig.steps.base.RunContext) ------------------------------------------

    @property
    def folder(self) -> Path:
        """The run folder."""
        assert self.writer is not None
        return self.writer.folder

    def event(self, level: str, message: str) -> None:
        """Record an event (info, warning, error, operator)."""
        self._event(level, message)

    def record_result(self, name: str, value: JsonObject) -> None:
        """Keep a result for later steps and store it."""
        assert self.writer is not None
        self.results[name] = value
        self.writer.set_result(name, value)

    def open_reader(self) -> RunReader:
        """The store as recorded so far (flushed first); the caller closes it."""
        assert self.writer is not None
        self.writer.flush()
        return RunReader(self.writer.folder)

    def scalar_magnetometer(self, name: str) -> ScalarMagnetometer:
        """Total-field magnetometer ``name`` of the rig, opened for this run (closed with it)."""
        assert self.rig is not None
        return self.rig.scalar_magnetometer(name)

    def live_forecast(self, step: Step, noise_nt: float) -> SigmaForecast | None:
        """A live step's sigmas forecast from its plan (rig.prediction.live_calibrate_stop); None when its plan
        cannot be fitted."""
        from rig.prediction.live_calibrate_stop import live_forecast

        return live_forecast(self.proc, step, self.cfg, self.runs_dir, noise_nt, self.results)

    def predict_after_null(self, null_name: str) -> None:
        """Beside the run, from its null hold: the calibrations to come predicted again when this
        DUT's noise differs from its history (rig.engine.after_null), kept in the run's meta."""
        from rig.engine.after_null import start_after_null

        start_after_null(self, null_name)

    def set_meta(self, **values: JsonValue) -> None:
        """Store run metadata (JSON values)."""
        assert self.writer is not None
        self.writer.set_meta(**values)

    def ask_operator(self, text: str) -> bool:
        """A yes/no question (:class:`OperatorChannel`)."""
        assert self.rig is not None and self.publisher is not None
        return self.operator.ask(self.rig, self.publisher, text)

    def request_report(self) -> None:
        """Write the acceptance report once the run is closed and sealed."""
        self.report_requested = True

    def command(self, step_idx: int, command: FieldCommand | LoadCommand, now: float,
                timing: Mapping[str, float] | None = None) -> None:  # fmt: skip
        """Carry out a field or load set-point (:class:`Commands`)."""
        assert self.commands is not None
        self.commands.command(step_idx, command, now, timing)
