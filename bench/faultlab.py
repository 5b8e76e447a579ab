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

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rig.config import load_rig_config
from rig.engine.runner import Runner
from rig.procedure.language import parse_procedure
from rig.sim_rig import sim_rig_config
from rig.store import RunReader
from sim.cage import SimulatedCage
from sim.config import load_config

PROCEDURE = """procedure: Fault matrix
parameters:
  dut_serial: {{default: FAULTS}}
magnetometers: {{dut: {dut}, reference: reference}}
loads: [load_bus, load_panel]
steps:
  - null_field: {{hold_s: 1}}
    name: noise floor
  - sphere_sweep: {{directions: 12, magnitude_ut: [20, 40], dwell_s: 0.5}}
    name: sweep
    loads:
      load_bus: {{steps: {{levels_a: [0.0, 1.0], dwell_s: 1.0}}}}
      load_panel: {{constant: {{current_a: 1.5}}}}
  - check:
      criteria:
        - {{result: noise floor, value: dut_noise_nt, max: 1000, name: DUT answers}}
"""
INJECT_AFTER_S = 1.5
"""Seconds into the sweep when the fault is injected."""

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
    mode: str = "in-process"  # in-process, sigkill, full-disk
    mentions: str = ""  # what the reason must name
    safe_within_ms: float = 0.0  # the bound the tests hold it to (0: the run completes)


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
          "error", _set("coil_x", silent=True), dead=("coil_x",), mentions="coil_x", safe_within_ms=5000),
    Fault("modbus-exception", "load_bus answers every request with exception 4 (device failure)",
          "aborts to the safe state naming load_bus and the exception", "error",
          _set("load_bus", exception_code=4), dead=("load_bus",), mentions="load_bus", safe_within_ms=2500),
    Fault("tcp-disconnect", "the TCP connection of coil_z is closed once",
          "reconnects and carries on; the run completes", "complete", _drop("coil_z"), mentions="", safe_within_ms=0),
    Fault("tcp-down", "coil_z closes every connection from now on",
          "aborts to the safe state naming coil_z", "error", _set("coil_z", disconnect=True),
          dead=("coil_z",), mentions="coil_z", safe_within_ms=1500),
    Fault("rtu-bad-crc", "10 % of coil_y's RTU replies have a flipped bit (bad CRC)",
          "retries the damaged transactions; the run completes", "complete",
          _set("coil_y", corrupt_rate=0.1), mentions="", safe_within_ms=0),
    Fault("serial-garbage", "20 % of HMR2300 frames damaged, 10 % cut short",
          "resynchronises on the frame stride; the run completes with the good frames",
          "complete", _set("dut", corrupt_rate=0.2, drop_rate=0.1), mentions="", safe_within_ms=0),
    Fault("hmr2300-stall", "the HMR2300 stream stops", "detects the stall within 1.5 s and aborts"
          " to the safe state naming dut", "error", _set("dut", silent=True), mentions="dut", safe_within_ms=3500),
    Fault("i2c-nack", "the RM3100 stops acknowledging on I2C",
          "aborts to the safe state naming rm3100", "error", _set("rm3100", silent=True),
          dut="rm3100", mentions="rm3100", safe_within_ms=1500),
    Fault("stuck-sensor", "the HMR2300 repeats its last reading",
          "detects 60 identical readings (3 s) and aborts naming dut", "error",
          _set("dut", stuck=True), mentions="frozen", safe_within_ms=5000),
    Fault("protection-trip", "load_bus trips its over-current protection",
          "detects the trip within 0.2 s and aborts to the safe state", "error",
          _trip("load_bus"), mentions="load_bus", safe_within_ms=1500),
    Fault("coil-trip", "the coil_x supply trips its over-current protection",
          "detects the trip within 1 s and aborts to the safe state", "error", _trip("coil_x"), mentions="coil x", safe_within_ms=3000),
    Fault("full-disk", "the run's files may not grow beyond 256 kB (RLIMIT_FSIZE)",
          "stops recording, aborts to the safe state, keeps what was committed", "error",
          mode="full-disk", mentions="disk", safe_within_ms=2500),
    Fault("sigkill", "SIGKILL of the rig process", "the guardian process switches every output"
          " off; the run reads back as incomplete", "incomplete", mode="sigkill", mentions="guardian", safe_within_ms=1500),
)  # fmt: skip


@dataclass
class Measured:
    """What a run did under one fault."""

    fault: Fault
    status: str
    exit_code: int
    reason: str
    time_to_safe_ms: float | None  # None: the run completed (outputs off at its normal end)
    samples_stored: int
    samples_lost: int | None  # received but not stored; None where unknowable (process killed)
    duration_s: float

    @property
    def problems(self) -> list[str]:
        """How the run departed from the fault's expected behaviour (none: as expected)."""
        f, out = self.fault, []
        if self.status != f.expect_status:
            out.append(f"status {self.status}, expected {f.expect_status} ({self.reason})")
        if self.samples_lost not in (0, None):
            out.append(f"{self.samples_lost} received samples not stored")
        if f.mentions and f.mentions not in self.reason:
            out.append(f"the reason does not name {f.mentions!r}: {self.reason}")
        if f.safe_within_ms and not (self.time_to_safe_ms or float("inf")) <= f.safe_within_ms:
            out.append(f"time to safe {self.time_to_safe_ms} ms, bound {f.safe_within_ms:g} ms")
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
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self, t0: float) -> None:
        self.t0 = t0
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.002):
            supplies = self.cage.physics.supplies
            if not any(s.output for n, s in supplies.items() if n not in self.dead):
                self.t_safe = time.monotonic()
                return

    def stop(self) -> float | None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(1.0)
        if self.t0 is None or self.t_safe is None:
            return None
        return 1000.0 * (self.t_safe - self.t0)


def _sweep_started(get_step: Callable[[], str | None], timeout_s: float = 30.0) -> float:
    deadline = time.monotonic() + timeout_s
    while get_step() != "sweep":
        if time.monotonic() > deadline:
            raise TimeoutError("the run never reached the sweep")
        time.sleep(0.01)
    return time.monotonic()


def run_fault(fault: Fault, workdir: Path) -> Measured:
    """Run the fault procedure with ``fault`` injected; return what happened."""
    workdir.mkdir(parents=True, exist_ok=True)
    cfg = load_config()
    with SimulatedCage(cfg) as cage:
        (workdir / "rig.toml").write_text(sim_rig_config(cage.endpoints_document(), cfg))
        proc_path = workdir / "faults.yaml"
        proc_path.write_text(PROCEDURE.format(dut=fault.dut))
        if fault.mode == "in-process":
            return _in_process(fault, cage, workdir, proc_path)
        return _child(fault, cage, workdir, proc_path)


def _in_process(fault: Fault, cage: SimulatedCage, workdir: Path, proc_path: Path) -> Measured:
    runner = Runner(parse_procedure(proc_path), load_rig_config(workdir / "rig.toml"),
                    workdir / "runs", i2c_bus=cage.i2c_bus, confirm=lambda s: True, live=False,
                    guardian=False)  # fmt: skip
    watch = _Watch(cage, fault.dead)

    def injector() -> None:
        t_sweep = _sweep_started(lambda: (getattr(runner, "current_step", None) or (0, ""))[1])
        time.sleep(max(0.0, t_sweep + INJECT_AFTER_S - time.monotonic()))
        assert fault.inject is not None
        fault.inject(cage)
        watch.start(time.monotonic())

    thread = threading.Thread(target=injector, daemon=True)
    thread.start()
    t0 = time.monotonic()
    outcome = runner.run()
    took = time.monotonic() - t0
    thread.join(1.0)
    time_to_safe = watch.stop() if outcome.status != "complete" else None
    reader = RunReader(outcome.folder)
    try:
        meta = reader.meta()
        received = sum(int(v) for k, v in meta.items() if k.startswith("samples_"))
        stored = reader.count("samples")
    finally:
        reader.close()
    return Measured(fault, outcome.status, outcome.exit_code, outcome.reason, time_to_safe,
                    stored, received - stored, took)  # fmt: skip


def _child(fault: Fault, cage: SimulatedCage, workdir: Path, proc_path: Path) -> Measured:
    runs = workdir / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    limit = 256 * 1024

    def limits() -> None:
        if fault.mode == "full-disk":
            import resource

            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    t0 = time.monotonic()
    child = subprocess.Popen([sys.executable, "-m", "rig.cli", "-q", "run", str(proc_path), "--rig",
                              str(workdir / "rig.toml"), "--yes", "--runs-dir", str(runs)],
                             stderr=subprocess.PIPE, text=True, preexec_fn=limits)  # fmt: skip
    watch = _Watch(cage, ())

    def step_of() -> str | None:
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

    t_fault: float | None = None
    if fault.mode == "sigkill":
        t_sweep = _sweep_started(step_of)
        time.sleep(max(0.0, t_sweep + INJECT_AFTER_S - time.monotonic()))
        t_fault = time.monotonic()
        watch.start(t_fault)
        child.send_signal(signal.SIGKILL)
    else:  # the fault is the file size limit: it strikes when the log reaches it
        while child.poll() is None and t_fault is None:
            wal = next(runs.glob("*/run.sqlite-wal"), None)
            if wal is not None and wal.exists() and os.path.getsize(wal) >= limit - 8192:
                t_fault = time.monotonic()
                watch.start(t_fault)
            time.sleep(0.002)
    _, err = child.communicate(timeout=60)
    took = time.monotonic() - t0
    time.sleep(0.5)  # the guardian finishes writing its record
    time_to_safe = watch.stop()
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
    if fault.mode == "sigkill" and t_fault is not None:
        events = [f"{e}; newest stored sample {1000 * (t_fault - newest):.0f} ms before the kill"
                  for e in events]  # fmt: skip
    if fault.mode == "full-disk":
        reason = next((line for line in err.splitlines() if "disk" in line), reason)
    elif events:
        reason = events[0]
    status = meta.get("status", "incomplete")
    if fault.mode == "full-disk" and status == "incomplete":
        status = "error" if child.returncode == 2 else status  # the status row could not be written
    return Measured(fault, status, child.returncode, reason, time_to_safe, stored, None, took)


def markdown(rows: list[Measured]) -> str:
    """The matrix as a Markdown table."""
    out = ["| fault | injected | expected | status (exit) | time to safe | samples stored / lost | reason given | as expected |",
           "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for m in rows:
        safe = "- (completed)" if m.time_to_safe_ms is None else f"{m.time_to_safe_ms:.0f} ms"
        lost = "?" if m.samples_lost is None else str(m.samples_lost)
        reason = m.reason.replace("|", "/")[:230]
        out.append(f"| {m.fault.key} | {m.fault.what} | {m.fault.expected} | {m.status} ({m.exit_code})"
                   f" | {safe} | {m.samples_stored} / {lost} | {reason} | {'yes' if m.ok else 'NO'} |")  # fmt: skip
    return "\n".join(out)
