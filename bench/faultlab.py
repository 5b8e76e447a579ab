"""The fault matrix: inject each fault into the simulated cage during a run, measure the outcome.

For every fault: what is injected, the expected behaviour (retry, resync, or abort to the safe
state), and what a run actually did: its status and exit code, the time from the fault to every
output being off (polled in the simulator's physics every 2 ms), the samples the rig received but
did not store, and the reason it gave. ``bench/fault_matrix.py`` runs all of them and writes
``docs/reliability.md``; ``tests/engine/test_fault_matrix.py`` runs the fast ones in CI.

A test harness, not part of the product: it lives beside the benchmark that runs it. The script
imports it as ``faultlab`` (a script's folder is on ``sys.path``), the tests as ``bench.faultlab``
(``python -m pytest`` runs from the project root, as for ``tests.simproc``).
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import timebase
from drivers.transport.tty_watch import tty_stall_s, tty_watch
from rig.config import load_rig_config
from rig.engine.cpu_wait import CpuWaitLog
from rig.engine.runner import Runner
from rig.procedure.language import parse_procedure
from rig.sim_rig import sim_rig_config
from rig.store import RunReader
from sim.cage import SimulatedCage
from sim.config import load_config

PREAMBLE = """procedure: Fault matrix ({kind})
parameters:
  dut_serial: {{default: FAULTS}}
magnetometers: {{dut: {dut}, reference: reference}}
loads: [load_bus, load_panel, heater]
steps:
  - null_field: {{hold_s: 1}}
    name: noise floor
"""
LOADS = """    loads:
      load_bus: {steps: {levels_a: [0.0, 1.0], dwell_s: 1.0}}
      load_panel: {constant: {current_a: 1.5}}
"""
HEATER = """    loads:
      heater: {steps: {levels_a: [2.0, 0.0], dwell_s: 6.0}}
"""
CHECK = """  - check:
      criteria:
        - {result: noise floor, value: dut_noise_nt, max: 1000, name: DUT answers}
"""
TLE = (
    '["1 25544U 98067A   19343.69339541  .00001764  00000-0  38792-4 0  9991",'
    ' "2 25544  51.6439 211.2001 0007417  17.6667  85.6398 15.50103472202482"]'
)
TARGETS: dict[str, str] = {
    "null_field": "null_field: {hold_s: 9}",
    "set_field": "set_field: {field_ut: [20, -15, 10], hold_s: 9}",
    "hold": "hold: {hold_s: 9}",
    "sphere_sweep": "sphere_sweep: {directions: 8, magnitude_ut: [20, 40], dwell_s: 0.5}",
    "axis_sweep": "axis_sweep: {axis: x, from_ut: -40, to_ut: 40, points: 13, dwell_s: 0.6}",
    "rotate": "rotate: {magnitude_ut: 40, points: 24, dwell_s: 0.35}",
    "orbit_replay": f"orbit_replay: {{tle: {TLE}, start: '2019-12-09T12:00:00Z', duration_s: 90,"
                    " time_scale: 10, rate_hz: 20, attitude: tumbling}",
    "live_calibrate": "live_calibrate: {method: ukf, telemetry: [load_bus, load_panel],"
                      " stop_on_target: 'no', min_s: 9, max_s: 9, magnitude_ut: [15, 45], dwell_s: 0.8}",
    "noise_spectrum": "noise_spectrum: {hold_s: 9, band_hz: [0.5, 5.0]}",
    "linearity": "linearity: {max_ut: 50, points: 5, dwell_s: 1.0}",  # loads switch mid-point
    "characterize_cage": "characterize_cage: {amplitude_a: 1.0, samples: 10, repeats: 1}",
    # turns the DUT's automatic set/reset off: back on however the step ends
    "perming": "perming: {shock_ut: 60, shock_s: 1, hold_s: 4, settle_s: 0.5}",
    # the heater warms the DUT, then lets it cool: a cycle in 12 s, judged in small bins
    "thermal_cycle": "thermal_cycle: {thermometer: dut_temp, hold_s: 12, settle_s: 0.3,"
                     " reversal_k: 0.05, bin_k: 0.02, bin_s: 1}",
    "frequency_response": "frequency_response: {frequencies_hz: [1.0], axes: x, cycles: 6, min_s: 0}",
}  # fmt: skip
"""The step each column of the matrix injects its faults into (named ``target``, about 9 s): every
step kind that drives outputs."""
STEP_KINDS = tuple(TARGETS)
INJECT_AFTER_S = 1.5
SECOND_RUN_HOLD_S = 20.0
"""How long the first run holds the rig after its target step while a second run tries it (s)."""
"""Seconds into the target step when the fault is injected."""


def procedure(kind: str, dut: str = "dut") -> str:
    """The fault procedure for step kind ``kind``: a noise floor, the target step (with load
    profiles where the kind takes them), a check."""
    from rig.steps import KINDS

    text = PREAMBLE.format(kind=kind, dut=dut)
    if kind == "hold":
        text += "  - set_field: {field_ut: [20, -15, 10], hold_s: 0.2}\n    name: setup\n"
    text += f"  - {TARGETS[kind]}\n    name: target\n"
    if kind == "thermal_cycle":
        text += HEATER
    elif KINDS[kind].takes_loads:
        text += LOADS
    return text + CHECK


Inject = Callable[[SimulatedCage], None]


@dataclass(frozen=True)
class Fault:
    """One row of the matrix."""

    key: str
    what: str  # what is injected
    expected: str  # what the rig must do
    expect_status: str  # complete, error, aborted, incomplete
    inject: Inject | None = None
    dead: tuple[str, ...] = ()  # outputs that cannot be switched off (the faulty device itself)
    dut: str = "dut"
    mode: str = "in-process"  # in-process, sigkill, sigstop, full-disk
    mentions: str = ""  # what the reason must name
    detect_within_ms: float = 0.0  # the stated detection bound (0: the run completes)


SAFE_AFTER_DETECTION_MS = 1000.0
"""Every output off within this long of the rig knowing of the fault, in every cell."""
LOST_DATA_MS = 500.0
"""At most this much recorded data (before the fault) may be missing from the store."""


def _set(device: str, **faults: Any) -> Inject:
    def inject(cage: SimulatedCage) -> None:
        for key, value in faults.items():
            setattr(cage.faults[device], key, value)

    return inject


def _drop(device: str) -> Inject:
    return lambda cage: cage.drop_connections(device)


def _trip(device: str) -> Inject:
    return lambda cage: cage.physics.supplies[device].trip(2)


FAULTS: tuple[Fault, ...] = (
    Fault("modbus-timeout", "coil_x supply stops answering (Modbus TCP, no reply)",
          "retries, then aborts to the safe state naming coil_x; every other output off",
          "error", _set("coil_x", silent=True), dead=("coil_x",), mentions="coil_x", detect_within_ms=5000),
    Fault("modbus-exception", "load_bus answers every request with exception 4 (device failure)",
          "aborts to the safe state naming load_bus and the exception", "error",
          _set("load_bus", exception_code=4), dead=("load_bus",), mentions="load_bus", detect_within_ms=1000),
    Fault("tcp-disconnect", "the TCP connection of coil_z is closed once",
          "reconnects and carries on; the run completes", "complete", _drop("coil_z"), mentions="", detect_within_ms=0),
    Fault("tcp-down", "coil_z closes every connection from now on",
          "aborts to the safe state naming coil_z", "error", _set("coil_z", disconnect=True),
          dead=("coil_z",), mentions="coil_z", detect_within_ms=2500),
    Fault("rtu-bad-crc", "10 % of coil_y's RTU replies have a flipped bit (bad CRC)",
          "retries the damaged transactions; the run completes", "complete",
          _set("coil_y", corrupt_rate=0.1), mentions="", detect_within_ms=0),
    Fault("serial-garbage", "20 % of HMR2300 frames damaged, 10 % cut short",
          "resynchronises on the frame stride; the run completes with the good frames",
          "complete", _set("dut", corrupt_rate=0.2, drop_rate=0.1), mentions="", detect_within_ms=0),
    Fault("hmr2300-stall", "the HMR2300 stream stops", "detects the stall within 1.5 s and aborts"
          " to the safe state naming dut", "error", _set("dut", silent=True), mentions="dut", detect_within_ms=2000),
    Fault("i2c-nack", "the RM3100 stops acknowledging on I2C",
          "aborts to the safe state naming rm3100", "error", _set("rm3100", silent=True),
          dut="rm3100", mentions="rm3100", detect_within_ms=1500),
    Fault("stuck-sensor", "the HMR2300 repeats its last reading",
          "detects 60 identical readings (3 s) and aborts naming dut", "error",
          _set("dut", stuck=True), mentions="frozen", detect_within_ms=3500),
    Fault("protection-trip", "load_bus trips its over-current protection",
          "detects the trip within 0.2 s and aborts to the safe state", "error",
          _trip("load_bus"), mentions="load_bus", detect_within_ms=500),
    Fault("coil-trip", "the coil_x supply trips its over-current protection",
          "detects the trip within 1 s and aborts to the safe state", "error", _trip("coil_x"), mentions="coil x", detect_within_ms=1500),
    Fault("full-disk", "the disk is full: the runs folder is a small tmpfs filled up (where mounts are not allowed: the rig's file-size limit set to the current size)",
          "stops recording, aborts to the safe state, keeps what was committed", "error",
          mode="full-disk", mentions="disk", detect_within_ms=1000),
    Fault("sigkill", "SIGKILL of the rig process", "the guardian process switches every output"
          " off; the run reads back as incomplete", "incomplete", mode="sigkill", mentions="guardian", detect_within_ms=200),
    Fault("hung", "the rig process stops (SIGSTOP: as a deadlock or a computation holding the"
          " interpreter)", "the guardian misses the heartbeat for 3 s, kills the rig and switches"
          " every output off", "incomplete", mode="sigstop", mentions="stopped answering", detect_within_ms=3500),
    Fault("config-edit-sigkill", "the rig configuration file edited (coil_x renamed, a line that is"
          " not TOML added), then SIGKILL of the rig process", "the guardian switches every output"
          " off from its frozen copy of the configuration; the run reads back as incomplete",
          "incomplete", mode="config-edit-sigkill", mentions="guardian", detect_within_ms=200),
    Fault("guardian-sigkill", "SIGKILL of the guardian process", "the rig sees it die, takes every"
          " output to the safe state and ends the run", "error", mode="guardian-sigkill",
          mentions="guardian process died", detect_within_ms=500),
)  # fmt: skip


@dataclass
class Measured:
    """What a run did under one fault during one step kind."""

    fault: Fault
    kind: str
    status: str
    exit_code: int
    reason: str
    time_to_safe_ms: float | None  # from the injection; None: the run completed normally
    detected_ms: float | None  # from the injection to the rig knowing; None: unknown or completed
    samples_stored: int
    samples_lost: int | None  # received but not stored; None where unknowable (process killed)
    data_lost_ms: float | None  # newest stored sample before a kill or stop (killed processes)
    duration_s: float
    outputs_left_on: tuple[str, ...] = ()  # outputs (other than dead ones) still on at the end
    kernel_stall_ms: float = 0.0  # of the time to safe, the kernel held serial data back (canary)
    rig_cpu_wait_ms: float = 0.0  # longest wait for a CPU of a rig thread in the 2 s before a kill
    # the guardian's own wait for a CPU while it acted (its account)
    guardian_cpu_wait_ms: float = 0.0
    # longest wait for a CPU of a rig thread from the fault until the rig ended (its safe path)
    rig_cpu_wait_after_ms: float = 0.0
    # why the fault was never injected ("": it was): the outcome then proves nothing
    not_injected: str = ""

    @property
    def safe_after_detection_ms(self) -> float | None:
        """From the rig knowing of the fault to every output off."""
        if self.time_to_safe_ms is None or self.detected_ms is None:
            return None
        return max(0.0, self.time_to_safe_ms - self.detected_ms)

    @property
    def problems(self) -> list[str]:
        """How the run departed from the fault's expected behaviour (none: as expected)."""
        f, out = self.fault, []
        if self.not_injected:
            return [f"the fault was never injected: {self.not_injected}"]
        if self.status != f.expect_status:
            out.append(f"status {self.status}, expected {f.expect_status} ({self.reason})")
        if self.outputs_left_on:
            out.append(f"left on: {', '.join(self.outputs_left_on)}")
        if self.samples_lost not in (0, None):
            out.append(f"{self.samples_lost} received samples not stored")
        if (
            self.data_lost_ms is not None
            and self.data_lost_ms > LOST_DATA_MS + self.rig_cpu_wait_ms
        ):
            out.append(f"newest stored sample {self.data_lost_ms:.0f} ms before the fault"
                       f" ({self.rig_cpu_wait_ms:.0f} ms of the rig waiting for a CPU)")  # fmt: skip
        if f.mentions and f.mentions not in self.reason:
            out.append(f"the reason does not name {f.mentions!r}: {self.reason}")
        if f.detect_within_ms:
            # a busy computer's kernel holding serial bytes back, or keeping the guardian from a
            # CPU, delays what no rig can hasten; both are measured, not guessed
            busy = self.kernel_stall_ms + self.guardian_cpu_wait_ms + self.rig_cpu_wait_after_ms
            why = (f"{self.kernel_stall_ms:.0f} ms of kernel serial stall,"
                   f" {self.guardian_cpu_wait_ms:.0f} ms of the guardian and"
                   f" {self.rig_cpu_wait_after_ms:.0f} ms of the rig waiting for a CPU")  # fmt: skip
            bound = f.detect_within_ms + SAFE_AFTER_DETECTION_MS + busy
            if self.time_to_safe_ms is None or self.time_to_safe_ms > bound:
                out.append(f"time to safe {self.time_to_safe_ms} ms, bound {bound:g} ms ({why})")
            after = self.safe_after_detection_ms
            if after is not None and after > SAFE_AFTER_DETECTION_MS + busy:
                out.append(f"safe {after:.0f} ms after detection ({why})")
        return out

    @property
    def ok(self) -> bool:
        """The run ended as the fault's expected behaviour says."""
        return not self.problems


class _Watch:
    """Polls the simulator's outputs every 2 ms from ``start()``: when were all of them off?"""

    def __init__(self, cage: SimulatedCage, dead: tuple[str, ...]) -> None:
        self.cage, self.dead = cage, dead
        self.t0: float | None = None
        self.t_safe: float | None = None
        self.kernel_stall_ms = 0.0
        if (
            not timebase.is_simulated()
        ):  # the harness's own canary: the kernel stalls the rig's links
            tty_watch()
        self._stop = timebase.Event()
        self._thread = timebase.Thread(self._run, name="outputs watch", daemon=True)

    def start(self, t0: float) -> None:
        self.t0 = t0
        self._thread.start()

    def on(self) -> tuple[str, ...]:
        """Outputs (not the dead ones) on right now."""
        supplies = self.cage.physics.supplies
        return tuple(n for n, s in supplies.items() if s.output and n not in self.dead)

    def _run(self) -> None:
        while not self._stop.wait(0.002):
            if not self.on():
                self.t_safe = timebase.monotonic()
                return

    def stop(self) -> float | None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(1.0)
        if self.t0 is None or self.t_safe is None:
            return None
        if not timebase.is_simulated():  # a simulated line has no kernel to stall it
            self.kernel_stall_ms = 1000.0 * tty_stall_s(self.t0, self.t_safe)
        return 1000.0 * (self.t_safe - self.t0)


def _current_step(runs: Path) -> str | None:
    """Name of the step the run under ``runs`` is in (None before its store exists)."""
    folder = next((p for p in runs.iterdir() if (p / "run.sqlite").exists()), None)
    if folder is None:
        return None
    try:
        reader = RunReader(folder)
        steps = reader.steps()
        reader.close()
    except Exception:  # the file may be mid-creation
        return None
    return steps[-1][1] if steps else None


def _target_started(get_step: Callable[[], str | None], timeout_s: float = 60.0,
                    child: subprocess.Popen[str] | None = None) -> float:  # fmt: skip
    """When the run enters its target step (the process's clock: simulated for a rig in this
    process); a run that ends before says why (its stderr)."""
    deadline = timebase.monotonic() + timeout_s
    while get_step() != "target":
        if child is not None and child.poll() is not None:
            _, err = child.communicate()
            raise RuntimeError(f"the run ended (exit {child.returncode}) before its target step:"
                               f" {err.strip()}")  # fmt: skip
        if timebase.monotonic() > deadline:
            raise TimeoutError("the run never reached the target step")
        timebase.sleep(0.01)
    return timebase.monotonic()


def run_fault(fault: Fault, workdir: Path, kind: str = "sphere_sweep") -> Measured:
    """Run the fault procedure of step kind ``kind`` with ``fault`` injected 1.5 s into it."""
    workdir.mkdir(parents=True, exist_ok=True)
    cfg = load_config()
    in_process = fault.mode == "in-process"
    # the rig in this process: the cage and the run on one simulated clock (ADR 0038); a rig
    # process of its own (killed, stopped, its disk filled) reaches the cage in real time
    with contextlib.ExitStack() as stack:
        if in_process:
            stack.enter_context(timebase.simulated())
        cage = stack.enter_context(SimulatedCage(cfg))
        (workdir / "rig.toml").write_text(sim_rig_config(cage.endpoints_document(), cfg))
        proc_path = workdir / "faults.yaml"
        proc_path.write_text(procedure(kind, fault.dut))
        if in_process:
            return _in_process(fault, kind, cage, workdir, proc_path)
        return _child(fault, kind, cage, workdir, proc_path)


def _in_process(
    fault: Fault, kind: str, cage: SimulatedCage, workdir: Path, proc_path: Path
) -> Measured:
    runner = Runner(parse_procedure(proc_path), load_rig_config(workdir / "rig.toml"),
                    workdir / "runs", i2c_bus=cage.i2c_bus, confirm=lambda s: True, live=False,
                    guardian=False)  # fmt: skip
    watch = _Watch(cage, fault.dead)
    t_inject: list[float] = []
    not_injected: list[str] = []

    def injector() -> None:
        try:
            t_target = _target_started(
                lambda: (getattr(runner, "current_step", None) or (0, ""))[1]
            )
        except TimeoutError as exc:  # the outcome then counts for nothing (Measured.problems)
            not_injected.append(str(exc))
            return
        timebase.sleep(max(0.0, t_target + INJECT_AFTER_S - timebase.monotonic()))
        assert fault.inject is not None
        t_inject.append(timebase.monotonic())
        fault.inject(cage)
        watch.start(t_inject[0])

    thread = timebase.Thread(injector, name="fault injection", daemon=True)
    thread.start()
    t0 = time.monotonic()
    outcome = runner.run()
    took = time.monotonic() - t0
    thread.join(1.0)
    if not t_inject and not not_injected:
        not_injected.append("the run ended before the fault was due")
    left_on = watch.on()
    time_to_safe = watch.stop() if outcome.status != "complete" else None
    reader = RunReader(outcome.folder)
    try:
        meta = reader.meta()
        received = sum(int(v) for k, v in meta.items() if k.startswith("samples_"))
        stored = reader.count("samples")
    finally:
        reader.close()
    detected = meta.get("t_end_detected")
    detected_ms = (
        1000.0 * (float(detected) - t_inject[0])
        if detected is not None and t_inject and outcome.status != "complete"
        else None
    )
    return Measured(fault, kind, outcome.status, outcome.exit_code, outcome.reason, time_to_safe,
                    detected_ms, stored, received - stored, None, took, left_on,
                    watch.kernel_stall_ms, not_injected=" ".join(not_injected))  # fmt: skip


def _fill_disk(folder: Path) -> None:
    """Write zeros into ``folder`` until its file system is full."""
    fd = os.open(folder / "filler", os.O_WRONLY | os.O_CREAT, 0o644)
    block = b"\0" * 65536
    try:
        while True:
            os.write(fd, block)
    except OSError:  # full: a last small write takes what is left
        with contextlib.suppress(OSError):
            while True:
                os.write(fd, b"\0" * 512)
    finally:
        os.close(fd)


def _small_filesystem(folder: Path, size_mb: int = 8) -> bool:
    """Mount a tmpfs of ``size_mb`` on ``folder`` (root only); False where mounts are refused."""
    folder.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        return False
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(folder)],
                          capture_output=True)  # fmt: skip
    return done.returncode == 0


def _child(
    fault: Fault, kind: str, cage: SimulatedCage, workdir: Path, proc_path: Path
) -> Measured:
    runs = workdir / "runs"
    mounted = fault.mode == "full-disk" and _small_filesystem(runs)
    runs.mkdir(parents=True, exist_ok=True)
    try:
        return _child_run(fault, kind, cage, workdir, proc_path, runs, mounted)
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(runs)], capture_output=True)


def _child_run(fault: Fault, kind: str, cage: SimulatedCage, workdir: Path, proc_path: Path,
               runs: Path, mounted: bool) -> Measured:  # fmt: skip
    t0 = time.monotonic()
    child = subprocess.Popen([sys.executable, "-m", "rig.cli", "-q", "run", str(proc_path), "--rig",
                              str(workdir / "rig.toml"), "--yes", "--runs-dir", str(runs)],
                             stderr=subprocess.PIPE, text=True)  # fmt: skip
    watch = _Watch(cage, ())

    t_target = _target_started(lambda: _current_step(runs), child=child)
    # the rig's threads' waits for a CPU up to the fault: a starved writer commits late, and a
    # kill then takes more than the commit interval with it (a busy computer, not the store)
    waits = CpuWaitLog(pid=child.pid)
    while time.monotonic() < t_target + INJECT_AFTER_S:
        waits.note(time.monotonic())
        time.sleep(max(0.0, min(0.1, t_target + INJECT_AFTER_S - time.monotonic())))
    waits.note(time.monotonic())
    if fault.mode == "config-edit-sigkill":
        rig_toml = workdir / "rig.toml"
        rig_toml.write_text(edit_config(rig_toml.read_text(encoding="utf-8")), encoding="utf-8")
    guardian = guardian_of(child.pid) if fault.mode == "guardian-sigkill" else None
    t_fault = time.monotonic()
    rig_cpu_wait_ms = 1000.0 * waits.waited_since(t_fault - 2.0)
    watch.start(t_fault)
    if fault.mode in ("sigkill", "config-edit-sigkill"):
        child.send_signal(signal.SIGKILL)
    elif guardian is not None:
        os.kill(guardian, signal.SIGKILL)
    elif fault.mode == "sigstop":
        child.send_signal(signal.SIGSTOP)
    elif mounted:
        _fill_disk(runs)
    else:  # no mounts here: every file of the rig may not grow from now on
        import resource

        folder = next(p for p in runs.iterdir() if (p / "run.sqlite").exists())
        size = max(p.stat().st_size for p in folder.iterdir() if p.is_file())
        resource.prlimit(child.pid, resource.RLIMIT_FSIZE, (size, size))
    _, err = _communicate_noting(child, waits)
    rig_cpu_wait_after_ms = 1000.0 * waits.waited_since(t_fault)
    took = time.monotonic() - t0
    deadline = time.monotonic() + 10  # the guardian finishes writing its record
    while watch.on() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)
    left_on = watch.on()
    time_to_safe = watch.stop()
    (runs / "filler").unlink(missing_ok=True)
    folder = next(p for p in runs.iterdir() if (p / "run.sqlite").exists())
    reader = RunReader(folder)
    try:
        meta = reader.meta()
        stored = reader.count("samples")
        reason = meta.get("reason", "")
        events = [m for _, lvl, m in reader.events() if lvl == "error"]
        newest = max(reader.samples(dev)[-1][0] for dev in reader.devices())
    finally:
        reader.close()
    detected_ms = None
    data_lost_ms = None
    if fault.mode in ("sigkill", "sigstop", "config-edit-sigkill"):
        data_lost_ms = max(0.0, 1000.0 * (t_fault - newest))
        guardian = next((e for e in events if e.startswith("guardian")), "")
        found = re.search(r" in (\d+) ms", guardian)
        if found and time_to_safe is not None:
            detected_ms = max(0.0, time_to_safe - float(found.group(1)))
        reason = guardian or reason
    elif "t_end_detected" in meta:
        detected_ms = 1000.0 * (float(meta["t_end_detected"]) - t_fault)
    if fault.mode == "full-disk":
        reason = next((line for line in err.splitlines() if "disk" in line), reason)
    status = meta.get("status", "incomplete")
    if fault.mode == "full-disk" and status == "incomplete":
        status = "error" if child.returncode == 2 else status  # the status row could not be written
    return Measured(fault, kind, status, child.returncode, reason, time_to_safe, detected_ms, stored,
                    None, data_lost_ms, took, left_on, watch.kernel_stall_ms,
                    rig_cpu_wait_ms, guardian_cpu_wait_ms(reason), rig_cpu_wait_after_ms)  # fmt: skip


def _communicate_noting(child: subprocess.Popen[str], waits: CpuWaitLog) -> tuple[str, str]:
    """``child.communicate`` (60 s at most) while ``waits`` notes the child's threads' waits for
    a CPU every 0.1 s: its safe path on a busy computer is slow by what no rig can hasten."""
    done = threading.Event()

    def note() -> None:
        while not done.wait(0.1) and child.poll() is None:
            waits.note(time.monotonic())

    noter = threading.Thread(target=note, daemon=True)
    noter.start()
    try:
        return child.communicate(timeout=60)
    finally:
        done.set()
        noter.join()


def edit_config(text: str) -> str:
    """The rig configuration edited as a careless user would during a run: coil_x renamed
    (everywhere), and a last line that is not TOML."""
    return text.replace('"coil_x"', '"coil_a"').replace("[devices.coil_x]", "[devices.coil_a]") + (
        "\nthis line is not TOML\n"
    )


def guardian_of(rig_pid: int) -> int:
    """The PID of the guardian of rig process ``rig_pid`` (its command line ends with it)."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"rig.engine.guardian" in argv and argv[-2:] == [str(rig_pid).encode(), b""]:
            return int(entry.name)
    raise RuntimeError(f"rig process {rig_pid} has no guardian")


EXTRA: tuple[Fault, ...] = (
    Fault("second-run", "a second `rig run` on the same rig while the first runs",
          "the second refuses in one line naming the first (command, PID, since); the first completes",
          "complete", mode="second-run", mentions="in use by"),
    Fault("cage-sigkill", "SIGKILL of `rig cage set-field 20 -15 10 --hold 60` while it holds the field",
          "its guardian switches every output off and the polarity relays back to normal", "safe",
          mode="cage-sigkill", mentions="guardian", detect_within_ms=200),
    Fault("coil-as-load", "a procedure drives coil_x as a load channel (ramp to 5 A; the cage allows"
          " 2.5 A and 120 uT), forced past the check of `rig check` and `rig run`",
          "the coil's own limits (the cage's) refuse the set-point beyond 2.5 A: nothing beyond"
          " it is sent, the run ends error naming coil_x and the limit", "error",
          mode="coil-as-load", mentions="beyond its 2.5 A limit", detect_within_ms=100),
)  # fmt: skip
"""Cells that are not a fault inside a step: the interlock, and the guardian of a cage command."""


def run_extra(fault: Fault, workdir: Path) -> Measured:
    """Run one of :data:`EXTRA`."""
    workdir.mkdir(parents=True, exist_ok=True)
    cfg = load_config()
    with SimulatedCage(cfg) as cage:
        rig_toml = workdir / "rig.toml"
        rig_toml.write_text(sim_rig_config(cage.endpoints_document(), cfg))
        if fault.mode == "second-run":
            return _second_run(fault, cage, workdir, rig_toml)
        if fault.mode == "coil-as-load":
            return _coil_as_load(fault, cage, workdir, rig_toml)
        return _cage_sigkill(fault, cage, rig_toml)


def _second_run(fault: Fault, cage: SimulatedCage, workdir: Path, rig_toml: Path) -> Measured:
    proc_path = workdir / "faults.yaml"
    # a hold after the target keeps the first run on the rig while the second starts: a second
    # `rig run` takes seconds to import on a busy computer, and one that finds the rig free
    # because the first had finished is right to run (seen beside two suites and CPU hogs)
    text = procedure("sphere_sweep")
    proc_path.write_text(text.replace(CHECK, f"  - hold: {{hold_s: {SECOND_RUN_HOLD_S:g}}}\n"
                                              "    name: keep the rig\n" + CHECK))  # fmt: skip
    runs, runs_b = workdir / "runs", workdir / "runs-b"
    runs.mkdir()
    t0 = time.monotonic()
    first = subprocess.Popen([sys.executable, "-m", "rig.cli", "-q", "run", str(proc_path), "--rig",
                              str(rig_toml), "--yes", "--runs-dir", str(runs)],
                             stderr=subprocess.PIPE, text=True)  # fmt: skip

    t_target = _target_started(lambda: _current_step(runs), child=first)
    time.sleep(max(0.0, t_target + INJECT_AFTER_S - time.monotonic()))
    second = subprocess.run([sys.executable, "-m", "rig.cli", "-q", "run", str(proc_path), "--rig",
                             str(rig_toml), "--yes", "--runs-dir", str(runs_b)],
                            capture_output=True, text=True, timeout=60)  # fmt: skip
    first.communicate(timeout=120)
    took = time.monotonic() - t0
    folder = next(p for p in runs.iterdir() if (p / "run.sqlite").exists())
    reader = RunReader(folder)
    try:
        status, stored = reader.meta().get("status", "?"), reader.count("samples")
    finally:
        reader.close()
    refused = second.returncode == 2 and not (runs_b.exists() and any(runs_b.iterdir()))
    reason = (
        second.stderr.strip() if refused else f"second run NOT refused (exit {second.returncode})"
    )
    return Measured(fault, "sphere_sweep", status, first.returncode, reason, None, None, stored,
                    None, None, took, tuple(n for n, s in cage.physics.supplies.items() if s.output))  # fmt: skip


def guardian_cpu_wait_ms(message: str) -> float:
    """The guardian's own wait for a CPU (ms) from its message (``waited N ms for a CPU``); 0."""
    found = re.search(r"waited (\d+) ms for a CPU", message)
    return float(found.group(1)) if found else 0.0


def killed_rig_end_ms(message: str) -> float:
    """How long a rig the guardian killed took to end (ms), from its message (``the killed rig
    took N ms to end``: the kernel's teardown, on a busy computer waiting for a CPU); 0."""
    found = re.search(r"the killed rig took (\d+) ms to end", message)
    return float(found.group(1)) if found else 0.0


def _cage_sigkill(fault: Fault, cage: SimulatedCage, rig_toml: Path) -> Measured:
    t0 = time.monotonic()
    child = subprocess.Popen([sys.executable, "-m", "rig.cli", "cage", "set-field", "--hold", "60",
                              "--rig-config", str(rig_toml), "--", "20", "-15", "10"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    assert child.stdout is not None
    line = child.stdout.readline()
    while line and not line.startswith("holding"):
        line = child.stdout.readline()
    watch = _Watch(cage, ())
    t_fault = time.monotonic()
    watch.start(t_fault)
    child.send_signal(signal.SIGKILL)
    _, err = child.communicate(timeout=60)  # returns once the guardian (holding stderr) exits
    took = time.monotonic() - t0
    left_on = watch.on()
    time_to_safe = watch.stop()
    relays = list(cage.physics.relays.sign)
    guardian = next((x for x in err.splitlines() if "guardian" in x), "no word from the guardian")
    found = re.search(r" in (\d+) ms", guardian)
    detected = time_to_safe - float(found.group(1)) if found and time_to_safe is not None else None
    status = "safe" if not left_on else "outputs on"
    if relays != [1, 1, 1]:
        status, guardian = "relay reversed", f"{guardian}; relay signs {relays}"
    return Measured(fault, "rig cage set-field", status, child.returncode or 0, guardian,
                    time_to_safe, detected, 0, None, None, took, left_on,
                    watch.kernel_stall_ms, 0.0, guardian_cpu_wait_ms(guardian))  # fmt: skip


COIL_AS_LOAD = """procedure: Coil as a load
parameters:
  dut_serial: {default: FAULTS}
magnetometers: {dut: dut, reference: reference}
loads: [coil_x]
steps:
  - set_field: {field_ut: [0, 0, 0], hold_s: 4}
    name: target
    loads:
      coil_x: {ramp: {from_a: 0.0, to_a: 5.0, step_s: 0.1}}
"""
"""The coil-as-load attack of issue 29 (the reference read +140 uT on x at coil_x's 3 A)."""


@contextlib.contextmanager
def _past_the_load_check() -> Iterator[None]:
    """The attack: ``Runner.run`` without its pre-run refusals (a cage device named as a load)
    and without its field guard (which would end it first: the reference reads 124.9 uT with the
    lab field), so the coil's own limits are what is measured."""
    import rig.engine.runner as runner_module

    check, guard = runner_module.refuse_what_check_refuses, runner_module.guard_the_field
    runner_module.refuse_what_check_refuses = lambda *args: None
    runner_module.guard_the_field = lambda *args: None
    try:
        yield
    finally:
        runner_module.refuse_what_check_refuses, runner_module.guard_the_field = check, guard


def _coil_as_load(fault: Fault, cage: SimulatedCage, workdir: Path, rig_toml: Path) -> Measured:
    proc_path = workdir / "coil-as-load.yaml"
    proc_path.write_text(COIL_AS_LOAD)
    coil = cage.physics.supplies["coil_x"]
    limit_a = load_rig_config(rig_toml).cage.max_current_a[0]  # type: ignore[union-attr]
    peak = [0.0]
    stop = threading.Event()

    def watch() -> None:  # the coil's current in the simulator's physics, every 2 ms
        while not stop.wait(0.002):
            peak[0] = max(peak[0], abs(coil.output_current()))

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    t0 = time.monotonic()
    try:
        with _past_the_load_check():
            outcome = Runner(parse_procedure(proc_path), load_rig_config(rig_toml), workdir / "runs",
                             i2c_bus=cage.i2c_bus, confirm=lambda s: True, live=False).run()  # fmt: skip
    finally:
        stop.set()
        watcher.join(1.0)
    took = time.monotonic() - t0
    reader = RunReader(outcome.folder)
    try:
        meta, stored = reader.meta(), reader.count("samples")
    finally:
        reader.close()
    refused = float(meta.get("t_end_detected", 0.0))  # the refused set-point: the "injection"
    left_on = tuple(n for n, s in cage.physics.supplies.items() if s.output)
    off = [s.off_since_s for s in cage.physics.supplies.values() if s.off_since_s is not None]
    time_to_safe = 1000.0 * (max(off) - refused) if off and not left_on and refused else None
    status = outcome.status
    if peak[0] > limit_a + 1e-6:
        status = f"coil_x at {peak[0]:.3f} A, beyond its {limit_a:g} A"
    reason = f"{outcome.reason} (coil_x peak {peak[0]:.3f} A)"
    return Measured(fault, "set_field", status, outcome.exit_code, reason, time_to_safe, 0.0,
                    stored, None, None, took, left_on)  # fmt: skip


def cells(full: bool) -> list[tuple[Fault, str]]:
    """The matrix: every fault during every step kind (``full``), or a diagonal for CI in which
    every fault and every step kind appears at least once."""
    if full:
        return [(f, k) for f in FAULTS for k in STEP_KINDS]
    return [(f, STEP_KINDS[i % len(STEP_KINDS)]) for i, f in enumerate(FAULTS)]


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def markdown(rows: list[Measured]) -> str:
    """The matrix: faults x step kinds (time to safe after detection), then every cell."""
    kinds = list(dict.fromkeys(m.kind for m in rows))
    faults = list(dict.fromkeys(m.fault.key for m in rows))
    by = {(m.fault.key, m.kind): m for m in rows}
    out = ["Each cell: detection / safe after detection, in ms from the injection; `ok` completed"
           " as expected; **NO** marks a cell that departed from its row.", "",
           "| fault | detection bound | " + " | ".join(kinds) + " |",
           "|---|---|" + "---|" * len(kinds)]  # fmt: skip
    for key in faults:
        f = next(m.fault for m in rows if m.fault.key == key)
        line = [key, f"{f.detect_within_ms:g} ms" if f.detect_within_ms else "- (completes)"]
        for kind in kinds:
            m = by.get((key, kind))
            if m is None:
                line.append("")
                continue
            cell = "ok" if m.time_to_safe_ms is None else (
                f"{_ms(m.detected_ms)} / {_ms(m.safe_after_detection_ms)}")  # fmt: skip
            line.append(cell if m.ok else f"**NO** {cell}")
        out.append("| " + " | ".join(line) + " |")
    out += ["", "| fault | step kind | expected | status (exit) | time to safe | samples stored /"
            " lost | data lost | reason given | as expected |", "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for m in rows:
        safe = "- (completed)" if m.time_to_safe_ms is None else f"{m.time_to_safe_ms:.0f} ms"
        lost = "?" if m.samples_lost is None else str(m.samples_lost)
        data = "-" if m.data_lost_ms is None else f"{m.data_lost_ms:.0f} ms"
        reason = m.reason.replace("|", "/")[:200]
        verdict = "yes" if m.ok else "NO: " + "; ".join(m.problems).replace("|", "/")[:200]
        out.append(f"| {m.fault.key} | {m.kind} | {m.fault.expected} | {m.status} ({m.exit_code})"
                   f" | {safe} | {m.samples_stored} / {lost} | {data} | {reason} | {verdict} |")  # fmt: skip
    return "\n".join(out)
