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
from rig import __version__
from rig.config import RigConfig
from rig.devices import build_cage, open_device
from rig.engine.analysis import calibrate_run, evaluate_criteria, noise_floor
from rig.engine.guardian import Guardian
from rig.engine.live import LiveView
from rig.engine.live_calibration import LiveCalibration
from rig.engine.sampling import BufferedSensor, SensorSampler
from rig.errors import RigError
from rig.procedure.language import Procedure
from rig.procedure.plan import StepPlan, compile_plan, rig_timing
from rig.store.run_store import RunReader, RunWriter, new_run

Confirm = Callable[[str], bool]
MONITOR_PERIOD_S = 0.2
STALL_S = 1.5
"""A sensor that sends nothing for this long (or 5 of its periods) has stalled."""
STUCK_AFTER = 60
"""This many identical readings in a row (3 s at 20 Hz) mean a frozen sensor: real noise varies.
A device's ``stuck_after`` in the rig configuration overrides it (0 = never)."""
OWN_STALL_S = 0.3
"""The monitor woke this much later than its period: our own process was descheduled."""
COIL_CHECK_S = 1.0
"""How often the coil supplies' protection flags are read."""


class RunAborted(RigError):  # noqa: N818 - an outcome, not a fault
    """The operator (Ctrl-C, SIGTERM, a declined prompt) stopped the run."""


@dataclass
class RunOutcome:
    """How a run ended."""

    status: str  # complete, failed (checks failed), aborted, error
    reason: str
    folder: Path
    results: dict[str, Any] = field(default_factory=dict)

    @property
    def exit_code(self) -> int:
        """0 complete, 1 checks failed, 2 error, 130 aborted."""
        return {"complete": 0, "failed": 1, "error": 2, "aborted": 130}.get(self.status, 2)


class Runner:
    """Runs one procedure on one rig."""

    def __init__(self, proc: Procedure, cfg: RigConfig, runs_dir: Path, *, i2c_bus: Any | None = None,
                 confirm: Confirm | None = None, quiet: bool = False, live: bool = True,
                 guardian: bool = True) -> None:  # fmt: skip
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
        self.loads: dict[str, Any] = {}
        self.commanded_loads: dict[str, float] = {}
        self.measured_loads: dict[str, tuple[float, float]] = {}  # name -> (time, A)
        self.live_cal: LiveCalibration | None = None
        self.report_requested = False
        self.fault: str | None = None
        self._coil_checked = 0.0
        self.samplers: dict[str, SensorSampler] = {}
        self.controller: Any = None
        self.live: LiveView | None = None

    # --- lifecycle ------------------------------------------------------------------------------

    def run(self) -> RunOutcome:
        """Execute the whole procedure; always returns an outcome with the run folder."""
        params = self.proc.parameters
        self.writer = w = new_run(
            self.runs_dir, params.get("dut_serial") or self.proc.path.stem,
            procedure=self.proc.title, procedure_file=self.proc.path.name, parameters=params,
            operator=params.get("operator", ""), dut_serial=params.get("dut_serial", ""),
            software_version=__version__, rig_config=str(self.cfg.path), magnetometers=self.proc.magnetometers,
            loads=list(self.proc.loads),
        )  # fmt: skip
        (w.folder / "procedure.yaml").write_text(self.proc.text, encoding="utf-8")
        shutil.copy(self.cfg.path, w.folder / "rig.toml")
        guardian = Guardian(self.cfg.path, w.folder) if self.use_guardian else None
        old = self._install_signals()
        status, reason = "error", "unknown"
        try:
            with ExitStack() as stack:
                self._open(stack)
                for plan in compile_plan(self.proc, rig_timing(self.cfg)):
                    self._execute(plan)
            verdict = self.results.get("verdict", {}).get("overall")
            status, reason = (
                ("failed", "acceptance checks failed")
                if verdict == "FAIL"
                else ("complete", "all steps done")
            )
        except (KeyboardInterrupt, RunAborted) as exc:
            status, reason = "aborted", str(exc) or "interrupted by the operator (Ctrl-C)"
        except (RigError, DeviceError) as exc:
            status, reason = "error", str(exc)
        except Exception as exc:  # record it, leave hardware safe (done above), then re-raise
            status, reason = "error", f"internal error: {type(exc).__name__}: {exc}"
            raise
        finally:
            if self.live is not None:
                self.live.stop()
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
            if guardian is not None:
                guardian.release()
            self._restore_signals(old)
        if self.report_requested:
            self._write_report(w.folder)
        return RunOutcome(status, reason, w.folder, self.results)

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
        self.writer.add_event(time.monotonic(), level, message)

    def _open(self, stack: ExitStack) -> None:
        """Open every device; register safe states and closes on ``stack`` (LIFO)."""
        w = self.writer
        assert w is not None
        self.controller = build_cage(self.cfg, stack, self.i2c_bus)
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
            if dev_name == cage_reference:
                driver = self.controller.reference
            else:
                driver = open_device(self.cfg.devices[dev_name], self.i2c_bus)
                stack.callback(driver.close)
            with contextlib.suppress(Exception):
                if not hasattr(driver, "fmt"):
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
            load = open_device(self.cfg.devices[name], self.i2c_bus)
            stack.callback(load.close)
            stack.callback(self._safe_load, name, load)
            load.set_current(0.0)
            if self.cfg.devices[name].kind == "riden-rd60xx":
                load.set_voltage(float(self.cfg.devices[name].get("compliance_v", 12.0)))
            load.set_output(True)
            self.loads[name] = load
            self.commanded_loads[name] = 0.0
            with contextlib.suppress(Exception):
                ident = load.identify()
                instruments[name] = f"{ident.model} {ident.serial}".strip()
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
                   cage_model=self.controller.model.to_dict())  # fmt: skip
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
        # Registered last so it runs first on the way out: the coils are ramped down and their
        # supplies switched off before anything else is stopped (safe() is idempotent).
        stack.callback(self._safe_cage)

    def _safe_cage(self) -> None:
        for problem in self.controller.safe():
            self._unsafe(f"cage did not go fully safe: {problem}")

    def _safe_load(self, name: str, load: Any) -> None:
        try:
            load.safe()
        except (DeviceError, OSError) as exc:
            self._unsafe(f"load {name} did not go safe: {exc}")

    def _unsafe(self, message: str) -> None:
        """An output that may still be on: recorded, and told to the operator whatever -q says."""
        self._event("error", message)
        print(f"rig: WARNING: {message}; switch it off by hand", file=sys.stderr)

    def _monitor(self, stop: threading.Event) -> None:
        """Read back load currents and watch the rig's health at about 5 Hz: a tripped supply, a
        stalled or frozen sensor or a store that cannot write ends the run (see ``fault``)."""
        w = self.writer
        assert w is not None
        last = time.monotonic()
        while not stop.wait(MONITOR_PERIOD_S):
            now = time.monotonic()
            # This thread woke late: the whole process was descheduled (a busy computer). The
            # samplers were too and need a moment to hand over what their sensors sent meanwhile,
            # so their freshness is judged on the next round, not now.
            own_stall = now - last > MONITOR_PERIOD_S + OWN_STALL_S
            last = now
            for name, load in list(self.loads.items()):
                try:
                    reading = load.read()
                    t_read = time.monotonic()
                    self.measured_loads[name] = (t_read, float(reading.i_out_a))
                    w.add_channel(
                        t_read, name, self.commanded_loads.get(name), float(reading.i_out_a)
                    )
                    if reading.protection:
                        self._fail(f"{name}: the output tripped ({reading.protection}) and is off;"
                                   " check the wiring and the load before running again")  # fmt: skip
                except (DeviceError, OSError) as exc:
                    self._event("warning", f"reading {name}: {exc}")
            self._check_health(w, judge_sensors=not own_stall)

    def _check_health(self, w: RunWriter, judge_sensors: bool = True) -> None:
        if w.error is not None:
            self._fail(f"cannot write the run data ({w.error}): is the disk full? Free space under"
                       f" {w.folder.parent}; what was recorded before is kept")  # fmt: skip
        now = time.monotonic()
        for name, sampler in list(self.samplers.items()) if judge_sensors else []:
            stall_s = max(STALL_S, 5.0 / sampler.rate_hz)
            stuck_after = int(self.cfg.devices[name].get("stuck_after", STUCK_AFTER)) or 10**9
            problem = sampler.health(now, stall_s, stuck_after)
            if problem is not None:
                self._fail(problem)
        ctl = self.controller
        if ctl is not None and ctl.enabled and self._coil_check_due(now):
            for axis, drive in enumerate(ctl.axes):
                try:
                    reading = drive.supply.read()
                except (DeviceError, OSError) as exc:
                    self._event("warning", f"reading the {'xyz'[axis]} coil supply: {exc}")
                    continue
                protection = reading.protection
                # the supply reads an unsigned current; a polarity relay gives it its sign
                sign = 1 if drive.bipolar else ctl.signs[axis]
                w.add_channel(time.monotonic(), f"coil_{'xyz'[axis]}", None,
                              sign * float(reading.i_out_a))  # fmt: skip
                if protection:
                    self._fail(f"coil {'xyz'[axis]} supply tripped ({protection}) and is off;"
                               " check the coil wiring, then run again")  # fmt: skip

    def _coil_check_due(self, now: float) -> bool:
        if now - self._coil_checked < COIL_CHECK_S:
            return False
        self._coil_checked = now
        return True

    def _fail(self, message: str) -> None:
        """A fault found off the main thread: the main thread raises it at its next wait."""
        if self.fault is None:
            self.fault = message

    # --- steps ----------------------------------------------------------------------------------

    def _wait_until(self, t_target: float, stop: threading.Event | None = None) -> float:
        """Sleep until ``t_target`` (monotonic) or until ``stop`` is set, honouring pause and
        abort; returns the time shift added by pauses."""
        shift = 0.0
        while True:
            if self.fault is not None:
                raise RigError(self.fault)
            if stop is not None and stop.is_set():
                return shift
            if self.abort.is_set():
                raise RunAborted("aborted")
            if self.paused.is_set():
                t_pause = time.monotonic()
                self._event("operator", "paused")
                while self.paused.is_set() and not self.abort.is_set():
                    time.sleep(0.05)
                shift += time.monotonic() - t_pause
                self._event("operator", "resumed")
                continue
            remaining = t_target + shift - time.monotonic()
            if remaining <= 0:
                return shift
            time.sleep(min(remaining, 0.05))

    def _execute(self, plan: StepPlan) -> None:
        w = self.writer
        assert w is not None
        step = plan.step
        t0 = time.monotonic()
        self.current_step = (step.index, step.name, t0, plan.duration_s)
        w.set_step(step.index, step.name, step.kind, t0, None)
        self._event("info", f"step {step.index + 1}/{len(self.proc.steps)}: {step.name}")
        live = self._start_live(step.params, t0) if step.kind == "live_calibrate" else None
        stop = live.done if live is not None else None
        try:
            for cmd in plan.commands:
                t0 += self._wait_until(t0 + cmd.t_s, stop)
                if stop is not None and stop.is_set():
                    break
                now = time.monotonic()
                if cmd.kind in ("field", "load"):
                    self.lateness_s.append(now - (t0 + cmd.t_s))
                self._command(step.index, cmd.kind, cmd.payload, now)
                if cmd.kind == "field" and step.kind in ("null_field", "set_field"):
                    t0 = time.monotonic() - cmd.t_s  # the hold starts once the field is there
        except BaseException:
            if live is not None:  # the run is ending: let go of the samplers and the worker
                self._detach_live(live)
                live.stop()
                self.live_cal = None
            raise
        if live is not None:
            self._end_live(live, plan)
        w.set_step(step.index, step.name, step.kind, self.current_step[2], time.monotonic())
        if live is not None:
            self._finish_live(live, step.name)
        if step.kind == "null_field":
            w.flush()
            reader = RunReader(w.folder)
            try:
                noise = noise_floor(
                    reader, (self.current_step[2], time.monotonic()), list(self.samplers), 0.3
                )
            finally:
                reader.close()
            mags = self.proc.magnetometers
            result = {f"{role}_noise_nt": noise[dev] for role, dev in mags.items() if dev in noise}
            self._result(step.name, result)

    def _start_live(self, params: dict[str, Any], t0: float) -> LiveCalibration:
        """Set up the filter of a ``live_calibrate`` step and connect it to the samplers."""
        mags = self.proc.magnetometers
        dut = mags.get(params["magnetometer"], params["magnetometer"])
        ref = mags.get("reference")
        if ref is None or dut not in self.samplers:
            raise RigError(
                f"{self.proc.path}: live_calibrate needs the '{params['magnetometer']}' and"
                " 'reference' magnetometers under 'magnetometers'"
            )
        noise_nt = params["noise_nt"] or self._noise_nt(params["magnetometer"])
        channels = list(params["telemetry"])
        live = LiveCalibration(
            params,
            noise_nt / 1000.0,
            t0,
            lambda t: self._loads_now(channels, live),
            self.correction,
        )
        self.samplers[ref].listeners.append(live.on_reference)
        self.samplers[dut].listeners.append(live.on_dut)
        live.start()
        self.live_cal = live
        self._event("info", f"live calibration: {params['method']} at {noise_nt:.3g} nT noise,"
                            f" targets {params['targets'] or 'none'}")  # fmt: skip
        return live

    def _noise_nt(self, role: str) -> float:
        """The newest noise floor of ``role`` combined with the reference's (nT, root sum square):
        the filter pairs each DUT sample with one reference sample, so both noises count."""
        for result in reversed(list(self.results.values())):
            if isinstance(result, dict) and f"{role}_noise_nt" in result:
                ref_nt = float(result.get("reference_noise_nt", 0.0))
                return float(math.hypot(result[f"{role}_noise_nt"], ref_nt))
        raise RigError(
            f"{self.proc.path}: live_calibrate needs the noise: put a null_field step before it,"
            " or give noise_nt"
        )

    def _loads_now(self, channels: list[str], live: LiveCalibration) -> np.ndarray:
        """Load currents (A) for the filter: the read-back once it is newer than the last change's
        settling, the commanded value before that."""
        out = []
        for ch in channels:
            meas = self.measured_loads.get(ch)
            fresh = meas is not None and meas[0] >= live.quiet_after
            out.append(meas[1] if fresh and meas is not None else self.commanded_loads[ch])
        return np.array(out, float)

    def _detach_live(self, live: LiveCalibration) -> None:
        for sampler in self.samplers.values():
            for fn in (live.on_dut, live.on_reference):
                if fn in sampler.listeners:
                    sampler.listeners.remove(fn)

    def _end_live(self, live: LiveCalibration, plan: StepPlan) -> None:
        """Disconnect the filter; after an early stop, switch the step's loads back to zero."""
        self._detach_live(live)
        if live.done.is_set():
            for ch in plan.step.loads:
                self._command(plan.step.index, "load", {"channel": ch, "current_a": 0.0},
                              time.monotonic())  # fmt: skip

    def _finish_live(self, live: LiveCalibration, name: str) -> None:
        assert self.writer is not None
        self.writer.flush()
        try:
            result = live.finish(self.writer.folder, name, time.monotonic())
        finally:
            self.live_cal = None
        self._result(name, result)
        self._event("info", f"live calibration '{name}' stopped: {result['live']['stopped']}")

    def _result(self, name: str, value: Any) -> None:
        assert self.writer is not None
        self.results[name] = value
        self.writer.set_result(name, value)

    def _command(self, step_idx: int, kind: str, payload: dict[str, Any], now: float) -> None:
        """Carry out one command; a live calibration ignores samples while a change is on."""
        live = self.live_cal
        if live is not None and kind in ("field", "load"):
            live.change_started(now)
        try:
            self._apply(step_idx, kind, payload, now)
        finally:
            if live is not None and kind in ("field", "load"):
                live.change_ended(time.monotonic())

    def _apply(self, step_idx: int, kind: str, payload: dict[str, Any], now: float) -> None:
        w = self.writer
        assert w is not None
        if kind == "field":
            target = np.array(payload["field_ut"])
            issued = now
            if payload.get("track"):
                # One tracked set-point moves the field by a slew-limited step that the reference
                # follows (interpolated): no interval to leave out. A ramp through zero is one.
                if not self.controller.track(target):
                    issued = time.monotonic()
            elif payload.get("trim"):
                result = self.controller.trim(target)
                if not result.settled:
                    self._event("warning", f"trim did not settle: {result.error_nt:.1f} nT")
            else:
                self.controller.set_field(target)
            # Logged when the ramp has finished: analysis counts settling from here.
            done = time.monotonic()
            w.add_command(done, step_idx, kind, payload | {"t_issued": min(issued, done)})
            for ax, amps in enumerate(self.controller.currents):
                w.add_channel(time.monotonic(), f"coil_{'xyz'[ax]}", float(amps), None)
        elif kind == "load":
            w.add_command(now, step_idx, kind, payload)
            name, amps = payload["channel"], float(payload["current_a"])
            self.loads[name].set_current(amps)
            self.commanded_loads[name] = amps
            w.add_channel(time.monotonic(), name, amps, None)
        elif kind == "prompt":
            text = payload["text"]
            if self.confirm is None:
                if not sys.stdin.isatty():
                    raise RigError(
                        f"the procedure asks the operator: {text!r}; run in a terminal, or pass --yes"
                    )
                ok = input(f"\n{text} [y/N] ").strip().lower() in ("y", "yes")
            else:
                ok = self.confirm(text)
            self._event("operator", f"prompt {text!r}: {'confirmed' if ok else 'declined'}")
            if not ok:
                raise RunAborted(f"the operator declined: {text}")
        elif kind == "calibrate":
            w.flush()
            reader = RunReader(w.folder)
            try:
                result = calibrate_run(reader, payload, self.proc.magnetometers, self.correction)
            finally:
                reader.close()
            name = self.proc.steps[step_idx].name
            self._result(name, result)
        elif kind == "characterize_cage":
            from rig.cage.characterize import characterize

            model = characterize(self.controller, payload["amplitude_a"], samples=payload["samples"],
                                 repeats=payload["repeats"])  # fmt: skip
            self.controller.model = model
            if self.cfg.cage is not None and self.cfg.cage.calibration is not None:
                version = model.save(self.cfg.cage.calibration)
                model.meta["file"] = str(version)
            w.set_meta(cage_model=model.to_dict())
            self._result(self.proc.steps[step_idx].name, {
                "k_ut_per_a": model.k_ut_per_a.tolist(), "b0_ut": model.b0_ut.tolist(),
                "k_sigma_ut_per_a": model.k_sigma.tolist(), "b0_sigma_ut": model.b0_sigma_ut.tolist(),
                "residual_rms_nt": model.meta["residual_rms_nt"],
                "condition_number": model.meta["condition_number"],
            })  # fmt: skip
        elif kind == "check":
            verdict = evaluate_criteria(self.results, payload["criteria"])
            self._result("verdict", verdict)
            for row in verdict["criteria"]:
                self._event(
                    "info" if row["verdict"] == "PASS" else "warning",
                    f"check {row['name']}: {row['verdict']}",
                )
        elif kind == "report":
            # Written once the run is closed and sealed, so it shows the final status and verdict
            # and the digest of the data as they will stay.
            self.report_requested = True
            self._event("info", "the report is written when the run closes")
        elif kind == "end":
            pass
        else:
            raise AssertionError(kind)
