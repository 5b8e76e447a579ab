"""A whole run of the engine in simulated time (ADR 0038, 0039), on a cage made of the tiny
devices of tests/drivers/wire_devices.py (three bipolar coil supplies on the simulated loopback
network and a reference magnetometer on a simulated serial line, whose field follows the coil
currents): the runner, the session, the samplers, the scheduler and the health monitor end the
run complete, dated in simulated time, with no guardian and the reason recorded; twice, with the
same record, the second time beside two CPU hogs. Wall times are printed, never asserted."""

from __future__ import annotations

import hashlib
import random
import struct
import time
from pathlib import Path

import numpy as np
import pytest

import timebase
from rig.config import load_rig_config
from rig.engine.runner import Runner
from rig.engine.session import NO_GUARDIAN_SIMULATED
from rig.procedure.language import parse_procedure
from rig.store.run_store import RunReader
from tests.drivers.wire_devices import Registers, cpu_hogs, serve_tcp
from timebase.wires import wires

K_UT_PER_A = np.diag([40.0, 39.0, 41.0])
AMBIENT_UT = np.array([20.0, -5.0, 44.0])
MODEL = 2005  # the bipolar supply's model register (regmaps/bipolar-supply.toml)

RIG_TOML = """
[cage]
axes = {{ x = "coil_x", y = "coil_y", z = "coil_z" }}
reference = "reference"
max_current_a = [2.0, 2.0, 2.0]
max_field_ut = 150.0
max_ambient_ut = 60.0
max_slew_a_per_s = 10.0
compliance_v = 12.0
nominal_k_ut_per_a = [[40.0, 0.0, 0.0], [0.0, 39.0, 0.0], [0.0, 0.0, 41.0]]
{coils}
[devices.reference]
kind = "ascii-mag"
protocol = "serial"
path = "simpipe://reference"
baudrate = 115200
rate_hz = 20.0
"""

COIL = """
[devices.coil_{axis}]
kind = "regmap-supply"
regmap = "bipolar-supply"
protocol = "modbus-tcp"
host = "127.0.0.1"
port = {port}
"""

PROCEDURE = """
procedure: Simulated time
parameters:
  operator: {default: nobody}
magnetometers: {dut: reference, reference: reference}
steps:
  - null_field: {hold_s: 3}
    name: null check
  - hold: {hold_s: 60}
    name: a minute
"""


def _coil(regs: dict[int, int]) -> None:
    """A bipolar supply's read-back follows its set-point while its output is on."""
    on = regs.get(0x12, 0) == 1
    regs[0x21] = regs.get(0x11, 0) if on else 0  # i_out = i_set (int16, mA)
    regs[0x20] = 500 if on else 0  # v_out 5 V


def _amps(regs: Registers) -> float:
    raw = regs.values.get(0x21, 0)
    return struct.unpack(">h", struct.pack(">H", raw))[0] / 1000.0


def _cage(folder: Path, reference_for_s: float = float("inf")) -> Path:
    """The devices on the current simulated clock, and the rig file naming them; the reference
    falls silent after ``reference_for_s`` (s)."""
    coils = [Registers({0x30: MODEL}, derive=_coil) for _ in range(3)]
    ports = [serve_tcp(regs) for regs in coils]
    end = wires().serve_serial("reference", baud=115200).device
    rng = random.Random(7)

    def reference() -> None:
        until = timebase.monotonic() + reference_for_s
        while not end.peer_closed and timebase.monotonic() < until:
            timebase.sleep(0.05)
            amps = np.array([_amps(r) for r in coils])
            field = K_UT_PER_A @ amps + AMBIENT_UT + [rng.gauss(0.0, 0.005) for _ in range(3)]
            try:
                end.write((" ".join(f"{v:+010.4f}" for v in field) + "\n").encode())
            except BrokenPipeError:  # the run has closed the port
                return

    timebase.Thread(reference, name="reference", daemon=True).start()
    rig_toml = folder / "rig.toml"
    rig_toml.write_text(RIG_TOML.format(coils="".join(
        COIL.format(axis=a, port=p) for a, p in zip("xyz", ports, strict=True))))  # fmt: skip
    return rig_toml


def _run(
    folder: Path, reference_for_s: float = float("inf")
) -> tuple[str, dict[str, object], list[tuple[float, str, str]], str]:
    folder.mkdir()
    (folder / "proc.yaml").write_text(PROCEDURE)
    with timebase.simulated(start_s=1000.0, epoch_s=1.9e9):
        rig_toml = _cage(folder, reference_for_s)
        proc = parse_procedure(folder / "proc.yaml")
        runner = Runner(proc, load_rig_config(rig_toml), folder / "runs", quiet=True, live=False)
        outcome = runner.run()
        sim_s = timebase.monotonic() - 1000.0
    reader = RunReader(outcome.folder)
    try:
        meta, events = reader.meta(), reader.events()
        rows = repr(
            (reader.dated_samples("reference"), reader.channel("coil_x"), reader.commands())
        )
    finally:
        reader.close()
    digest = f"{meta['samples_reference']} samples, {sim_s:.6f} s, {hashlib.sha256(rows.encode()).hexdigest()[:16]}"
    return f"{outcome.status}: {outcome.reason}", meta, events, digest


def test_a_run_in_simulated_time_completes_with_the_same_record_under_load(
    tmp_path: Path,
) -> None:
    wall0 = time.monotonic()
    status, meta, events, digest = _run(tmp_path / "idle")
    wall_idle = time.monotonic() - wall0
    assert status == "complete: all steps done", events
    assert meta["clock"] == "simulated"
    assert meta["start_time"].startswith("2030-03-17T17:46:40")  # epoch 1.9e9 s
    assert "guardian" not in meta
    assert ("info", NO_GUARDIAN_SIMULATED) in [(lv, m) for _, lv, m in events]
    assert meta["samples_reference"] == pytest.approx(20 * 63, abs=60)  # 20 Hz for ~63 s
    with cpu_hogs(2):
        wall1 = time.monotonic()
        again = _run(tmp_path / "hogs")
        wall_hogs = time.monotonic() - wall1
    assert again[0] == status and again[3] == digest
    assert [(t, lv, m) for t, lv, m in again[2]] == events  # the same events at the same times
    print(f"a run of {digest}: {wall_idle:.1f} s of wall time idle, {wall_hogs:.1f} s beside"
          " two CPU hogs")  # fmt: skip


def test_a_sensor_that_falls_silent_ends_the_run_through_the_safe_path_on_time(
    tmp_path: Path,
) -> None:
    status, meta, events, _ = _run(tmp_path / "silent", reference_for_s=20.0)
    assert status.startswith("error: reference: sampling stopped"), status
    # the last line at 1020 s, the sampler gives up after two 0.5 s timeouts, the health monitor
    # sees it at its next 0.2 s round, the main thread at its next 50 ms look
    detected = float(meta["t_end_detected"])  # type: ignore[arg-type]
    assert 1021.0 <= detected <= 1021.0 + 0.2 + 0.05 + 1e-6
    assert meta["status"] == "error"
    outputs = [m for _, lv, m in events if "read back" in m]
    assert outputs and "off" in outputs[-1], events
