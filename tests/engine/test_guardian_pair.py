"""The rig and its guardian watch each other, on the simulated cage over real Modbus, with real
processes and signals:

* the guardian acts on the configuration the rig parsed, frozen at start: the file edited during
  the run (a line that breaks its syntax, a renamed device) does not stop it switching every
  output off when the rig is SIGKILLed or stopped;
* a guardian that dies is a fault: the run takes its outputs safe and ends ``error``;
* a guardian that cannot read its configuration: the command refuses to start.

Times to safe are read on the supplies' side: the simulator records when each output went off
(``Supply.off_since_s``, its monotonic clock, which is this computer's), and nothing is discounted.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench.faultlab import guardian_cpu_wait_ms, guardian_of
from rig.config import load_rig_config
from rig.engine.guardian import HEARTBEAT_TIMEOUT_S, GuardianError
from rig.engine.session import RigSession
from rig.store import RunReader
from sim.cage import SimulatedCage
from tests.computer_delay import ComputerDelay
from tests.simproc import outputs

RIG = [sys.executable, "-m", "rig.cli"]
OUTPUTS_OFF_WITHIN_S = 1.0
PROCEDURE = """procedure: Guardian pair
magnetometers: {dut: dut, reference: reference}
loads: [load_bus]
steps:
  - set_field: {field_ut: [20, -15, 10], hold_s: 60}
    name: target
    loads:
      load_bus: {constant: {current_a: 1.0}}
"""
EDITS = {
    "invalid line": lambda text: text + "\nthis line is not TOML\n",
    "renamed device": lambda text: text.replace("[devices.coil_x]", "[devices.coil_a]").replace(
        'x = "coil_x"', 'x = "coil_a"'
    ),
}
DRIVEN = ("coil_x", "coil_y", "coil_z", "load_bus")


pytestmark = [pytest.mark.realtime, pytest.mark.usefixtures("own_lock_dir")]


def start_run(rig_toml: Path, tmp_path: Path) -> tuple[subprocess.Popen[str], Path]:
    """`rig run` of PROCEDURE as a child process, once its field and load are on: (child, runs)."""
    proc, runs = tmp_path / "pair.yaml", tmp_path / "runs"
    proc.write_text(PROCEDURE)
    child = subprocess.Popen([*RIG, "-q", "run", str(proc), "--rig", str(rig_toml), "--yes",
                              "--runs-dir", str(runs)], stderr=subprocess.PIPE, text=True)  # fmt: skip
    wait_for_field(child, runs)
    return child, runs


def start_set_field(rig_toml: Path) -> subprocess.Popen[str]:
    """`rig cage set-field 20 -15 10 --hold 60`, once it holds the field."""
    child = subprocess.Popen([*RIG, "cage", "set-field", "--hold", "60", "--rig-config",
                              str(rig_toml), "--", "20", "-15", "10"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)  # fmt: skip
    assert child.stdout is not None
    line = child.stdout.readline()
    while line and not line.startswith("holding"):
        line = child.stdout.readline()
    assert line.startswith("holding"), child.communicate(timeout=30)
    return child


def wait_for_field(child: subprocess.Popen[str], runs: Path) -> None:
    """Until the run's target step has set its field and load (its store says so)."""
    deadline = time.monotonic() + 60
    while True:
        if child.poll() is not None:
            raise AssertionError(f"the run ended early: {child.communicate()[1]}")
        assert time.monotonic() < deadline, "the run never set its field"
        folder = next((p for p in runs.glob("*") if (p / "run.sqlite").exists()), None)
        if folder is not None:
            try:
                reader = RunReader(folder)
                try:
                    kinds = {c[2] for c in reader.commands()}
                finally:
                    reader.close()
            except Exception:  # the store is still being made
                kinds = set()
            if {"field", "load"} <= kinds:
                return
        time.sleep(0.05)


def off_after(cage: SimulatedCage, t0: float, names: tuple[str, ...], within_s: float) -> float:
    """Seconds from ``t0`` until the last of ``names`` went off, as the supplies recorded it;
    waits (at most ``within_s`` of this test's time, generous: a busy computer) for them."""
    supplies = cage.physics.supplies
    deadline = time.monotonic() + within_s
    while any(supplies[n].output for n in names):
        assert time.monotonic() < deadline, f"still on: {[n for n in names if supplies[n].output]}"
        time.sleep(0.01)
    off = [supplies[n].off_since_s for n in names]
    assert all(t is not None for t in off)
    return max(t for t in off if t is not None) - t0


def read_back_off(cage: SimulatedCage) -> None:
    """Every supply and load reads back off over Modbus (the guardian has released the ports)."""
    devices = cage.endpoints_document()["devices"]
    assert set(outputs(devices).values()) == {0}, outputs(devices)


@pytest.mark.parametrize("edit", list(EDITS))
@pytest.mark.parametrize("command", ["rig run", "rig cage set-field"])
def test_config_edited_then_sigkill_outputs_off_within_1_s(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path, edit: str, command: str
) -> None:
    if command == "rig run":
        child, _ = start_run(rig_toml, tmp_path)
    else:
        child = start_set_field(rig_toml)
    assert all(cage.physics.supplies[n].output for n in DRIVEN[:3])
    rig_toml.write_text(EDITS[edit](rig_toml.read_text()))
    t_kill, computer = time.monotonic(), ComputerDelay()
    child.send_signal(signal.SIGKILL)
    took = off_after(cage, t_kill, DRIVEN if command == "rig run" else DRIVEN[:3], 30.0)
    theirs = computer.seconds()
    _, err = child.communicate(timeout=60)  # the guardian holds the rig's stderr until it ends
    assert "Traceback" not in err, err
    assert re.search(r"rig guardian: the rig process died without going safe; switched off"
                     r" coil_x, coil_y, coil_z, trim_x, trim_y, trim_z, load_bus", err), err  # fmt: skip
    assert cage.physics.relays.sign == [1, 1, 1]
    read_back_off(cage)
    print(f"{command}, {edit}: outputs off {1000 * took:.0f} ms after SIGKILL")
    # less what the computer spent: this process's (the cage's) waits and the guardian's own
    assert took - theirs - guardian_cpu_wait_ms(err) / 1000.0 < OUTPUTS_OFF_WITHIN_S, err


def test_config_edited_then_sigstop_the_guardian_kills_and_switches_off(
    cage: SimulatedCage, rig_toml: Path
) -> None:
    child = start_set_field(rig_toml)
    rig_toml.write_text(EDITS["invalid line"](rig_toml.read_text()))
    t_stop, computer = time.monotonic(), ComputerDelay()
    child.send_signal(signal.SIGSTOP)
    took = off_after(cage, t_stop, DRIVEN[:3], HEARTBEAT_TIMEOUT_S + 30.0)
    theirs = computer.seconds()
    _, err = child.communicate(timeout=60)
    assert child.returncode == -signal.SIGKILL
    assert "Traceback" not in err, err
    said = re.search(r"no heartbeat for ([0-9.]+) s(?:, ([0-9.]+) s more while the guardian"
                     r" waited for a CPU)?.*switched off coil_x", err)  # fmt: skip
    assert said, err
    silent_s = float(said.group(1)) + float(said.group(2) or 0.0)
    read_back_off(cage)
    print(f"SIGSTOP, config edited: outputs off {took:.2f} s after the stop")
    assert took - theirs < silent_s + OUTPUTS_OFF_WITHIN_S, err


def test_guardian_sigkilled_the_run_goes_safe_and_ends_error_within_1_s(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path
) -> None:
    child, runs = start_run(rig_toml, tmp_path)
    guardian = guardian_of(child.pid)
    folder = next(p for p in runs.iterdir() if (p / "run.sqlite").exists())
    t_kill, computer = time.monotonic(), ComputerDelay(child.pid)
    os.kill(guardian, signal.SIGKILL)
    took = off_after(cage, t_kill, DRIVEN, 30.0)
    theirs = computer.seconds()  # the rig acts: its waits and the cage's
    while True:  # the run's status, as a reader sees it (this test's time: generous bound)
        reader = RunReader(folder)
        try:
            meta = reader.meta()
        finally:
            reader.close()
        t_status = time.monotonic() - t_kill
        if meta.get("status") not in (None, "running") or t_status > 30.0:
            break
        time.sleep(0.01)
    _, err = child.communicate(timeout=60)
    assert child.returncode == 2, err
    assert meta["status"] == "error", meta
    assert meta["reason"].startswith("the guardian process died (killed by SIGKILL); outputs"
                                     " switched off"), meta["reason"]  # fmt: skip
    detected = float(meta["t_end_detected"]) - t_kill  # the rig's own clock: when it knew
    assert cage.physics.relays.sign == [1, 1, 1]
    read_back_off(cage)
    print(f"guardian SIGKILL: detected {1000 * detected:.0f} ms, outputs off {1000 * took:.0f} ms,"
          f" run status error {1000 * t_status:.0f} ms after")  # fmt: skip
    assert detected < took and took - theirs < OUTPUTS_OFF_WITHIN_S, err
    assert t_status < 5.0  # a busy computer delays the closing of the store, not the outputs


def test_guardian_sigkilled_during_set_field_ends_it(cage: SimulatedCage, rig_toml: Path) -> None:
    child = start_set_field(rig_toml)
    guardian = guardian_of(child.pid)
    t_kill, computer = time.monotonic(), ComputerDelay(child.pid)
    os.kill(guardian, signal.SIGKILL)
    took = off_after(cage, t_kill, DRIVEN[:3], 30.0)
    theirs = computer.seconds()  # the rig acts: its waits and the cage's
    _, err = child.communicate(timeout=60)
    assert child.returncode == 2
    assert (
        err.strip()
        .splitlines()[-1]
        .startswith("rig: error: the guardian process died (killed by SIGKILL)")
    ), err
    # beside two hogs and a full suite once 1109 ms, none of it left out
    assert took - theirs < OUTPUTS_OFF_WITHIN_S, (err, theirs)


def test_guardian_stopped_is_a_fault_too(cage: SimulatedCage, rig_toml: Path) -> None:
    """A stopped guardian would not act if rig died: the rig sees its state within a heartbeat
    period, goes safe and ends; the stopped guardian is killed (it holds the interlock)."""
    child = start_set_field(rig_toml)
    guardian = guardian_of(child.pid)
    t_stop, computer = time.monotonic(), ComputerDelay(child.pid)
    os.kill(guardian, signal.SIGSTOP)
    took = off_after(cage, t_stop, DRIVEN[:3], 30.0)
    theirs = computer.seconds()
    _, err = child.communicate(timeout=60)
    assert child.returncode == 2
    assert (
        err.strip()
        .splitlines()[-1]
        .startswith(
            "rig: error: the guardian process is stopped (SIGSTOP, or a debugger holds it); outputs"
            " switched off"
        )
    ), err
    assert not Path(f"/proc/{guardian}").exists()
    print(f"guardian SIGSTOP: outputs off {1000 * took:.0f} ms after")
    assert took - theirs < OUTPUTS_OFF_WITHIN_S, (err, theirs)


def test_a_guardian_that_cannot_read_its_configuration_refuses_the_session(
    cage: SimulatedCage, rig_toml: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What the rig sends is not a configuration the guardian can read: the session refuses to
    start (one line) and nothing is switched on."""
    import rig.engine.guardian as guardian_module

    monkeypatch.setattr(guardian_module, "freeze", lambda cfg: '{"devices": 1}')
    writes = {n: s.writes for n, s in cage.physics.supplies.items()}
    session = RigSession(load_rig_config(rig_toml), command="test")
    with pytest.raises(GuardianError) as refused, session as rig:
        rig.cage().set_field([10.0, 0.0, 0.0])
    message = str(refused.value)
    assert message.startswith("the guardian process could not start (exit status 2)"), message
    assert "nothing was switched on" in message and "\n" not in message
    assert {n: s.writes for n, s in cage.physics.supplies.items()} == writes


def test_the_frozen_copy_is_the_configuration_as_parsed(rig_toml: Path) -> None:
    from dataclasses import replace

    from rig.engine.frozen_config import FrozenConfigError, freeze, thaw

    rig_toml.write_text(rig_toml.read_text() + '\n[lab]\nurl = "postgresql://u:secret@h/db"\n')
    cfg = load_rig_config(rig_toml)
    text = freeze(cfg)
    assert "\n" not in text and "secret" not in text
    assert thaw(text) == replace(cfg, raw={})
    with pytest.raises(FrozenConfigError, match="not a frozen rig configuration"):
        thaw('{"path": "x", "devices": {"a": {"kind": "k"}}, "cage": null}')
