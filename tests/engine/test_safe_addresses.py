"""`rig safe` depends on nothing but the device addresses (issue 51): with coils driven, the
heater at 2 A, both loads on and the x relay reversed (through the drivers, as a rig and guardian
that both died leave them), one bad key elsewhere in the rig file - a ``nan`` field limit, a
heater limit of -1, a two-element ``max_current_a``, a TOML typo, a 5000-deep array - does not
stop it: every supply and load is off in the simulator's physics afterwards, each output is read
back in one line, and the exit status is 0. A device whose own table is broken is named (exit
2) and does not stop the others. Real Modbus over loopback and ptys; the truth from
``cage.physics``."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from rig.config import load_rig_config
from rig.devices import open_device
from rig.engine.config_copy import copy_name, last_config_copy
from rig.engine.interlock import lock_dir
from rig.engine.session import RigSession
from rig.errors import UserInputError
from sim.cage import SimulatedCage

RIG = [sys.executable, "-m", "rig.cli"]
OUTPUTS = ("coil_x", "coil_y", "coil_z", "trim_x", "trim_y", "trim_z", "load_bus", "load_panel",
           "heater", "polarity")  # fmt: skip


def _after(header: str, line: str) -> Callable[[str], str]:
    return lambda text: text.replace(header + "\n", f"{header}\n{line}\n", 1)


BAD_KEYS: dict[str, Callable[[str], str]] = {
    "nan field limit": lambda t: t.replace("max_field_ut = 120.0", "max_field_ut = nan"),
    "heater limit -1": _after("[devices.heater]", "max_current_a = -1"),
    "two-element max_current_a": lambda t: t.replace(
        "max_current_a = [2.5, 2.5, 2.5]", "max_current_a = [2.5, 2.5]"
    ),
}
UNPARSABLE: dict[str, Callable[[str], str]] = {
    "TOML typo": lambda t: t.replace("max_slew_a_per_s = 10.0", "max_slew_a_per_s = = 10.0"),
    "5000-deep array": lambda t: t + "\ndeep = " + "[" * 5000 + "]" * 5000 + "\n",
}

pytestmark = [pytest.mark.realtime, pytest.mark.usefixtures("own_lock_dir")]


@pytest.fixture(autouse=True)
def everything_off_after(cage: SimulatedCage) -> Iterator[None]:
    """Leave the module's cage off whatever a test did (it is shared by the module's tests)."""
    yield
    for supply in cage.physics.supplies.values():
        supply.set_output(False)
    cage.physics.relays.sign = [1, 1, 1]


def drive_everything(rig_toml: Path) -> None:
    """Coils at 1 A, the heater at 2 A, both loads at 1 A and the x relay reversed, through the
    drivers, then the links closed with the outputs on (the processes that drove them died)."""
    cfg = load_rig_config(rig_toml)
    relay = open_device(cfg.devices["polarity"])
    try:
        relay.set_polarity(0, -1)  # first: a hot switch would trip the coil
    finally:
        relay.close()
    for name in ("coil_x", "coil_y", "coil_z", "trim_x", "heater", "load_bus", "load_panel"):
        drv = open_device(cfg.devices[name])
        try:
            if name == "load_panel":
                drv.enable_as_load(12.0)
                drv.set_current(1.0)
                continue
            drv.set_voltage(12.0)
            drv.set_current(2.0 if name == "heater" else 1.0 if name != "trim_x" else 0.3)
            drv.set_output(True)
        finally:
            drv.close()


def assert_driven(cage: SimulatedCage) -> None:
    supplies = cage.physics.supplies
    deadline = time.monotonic() + 2.0  # the coils' current rises with their L/R
    while supplies["heater"].output_current() < 1.9 and time.monotonic() < deadline:
        time.sleep(0.02)
    on = [n for n in ("coil_x", "coil_y", "coil_z", "heater", "load_bus", "load_panel")
          if supplies[n].output]  # fmt: skip
    assert len(on) == 6, on
    assert supplies["heater"].output_current() > 1.9
    assert cage.physics.relays.sign[0] == -1


def rig_safe(rig_toml: Path) -> tuple[subprocess.CompletedProcess[str], float]:
    """`rig safe` as a child process: (its result, monotonic s when it was started)."""
    t0 = time.monotonic()
    done = subprocess.run([*RIG, "safe", "--rig", str(rig_toml)], capture_output=True,
                          text=True, timeout=60)  # fmt: skip
    return done, t0


def off_after(cage: SimulatedCage, t0: float) -> float:
    """Seconds from ``t0`` until the last supply or load went off, as the simulator recorded it."""
    off = [s.off_since_s for s in cage.physics.supplies.values() if s.off_since_s is not None]
    return max(off) - t0


def assert_all_off(cage: SimulatedCage) -> None:
    supplies = cage.physics.supplies
    assert not [n for n, s in supplies.items() if s.output], "outputs still on"
    assert max(abs(s.output_current()) for s in supplies.values()) < 0.01
    assert cage.physics.relays.sign == [1, 1, 1]


def assert_read_back_lines(stdout: str) -> None:
    for name in OUTPUTS:
        want = rf"^{name}: off \(normal\)$" if name == "polarity" else (
            rf"^{name}: off \(0\.0(0\d|10) A read back\)$")  # fmt: skip
        assert re.search(want, stdout, re.M), (name, stdout)


@pytest.mark.parametrize("bad", list(BAD_KEYS))
def test_one_bad_key_elsewhere_does_not_stop_rig_safe(
    cage: SimulatedCage, rig_toml: Path, bad: str
) -> None:
    drive_everything(rig_toml)
    assert_driven(cage)
    rig_toml.write_text(BAD_KEYS[bad](rig_toml.read_text()))
    with pytest.raises(UserInputError):  # every other command refuses the file
        load_rig_config(rig_toml)
    done, t0 = rig_safe(rig_toml)
    took = time.monotonic() - t0
    assert done.returncode == 0, done
    assert done.stderr == "", done.stderr
    assert_all_off(cage)
    assert_read_back_lines(done.stdout)
    print(f"{bad}: rig safe: last output off {off_after(cage, t0):.2f} s after its start"
          f" (interpreter start-up included), done and read back in {took:.2f} s")  # fmt: skip


@pytest.mark.parametrize("bad", list(UNPARSABLE))
def test_an_unparsable_file_is_replaced_by_the_last_runs_copy(
    cage: SimulatedCage, rig_toml: Path, bad: str
) -> None:
    with RigSession(load_rig_config(rig_toml), command="test", guardian=False):
        pass  # a run used the file: its copy is kept
    assert (lock_dir() / copy_name(rig_toml)).is_file()
    drive_everything(rig_toml)
    assert_driven(cage)
    rig_toml.write_text(UNPARSABLE[bad](rig_toml.read_text()))
    done, t0 = rig_safe(rig_toml)
    took = time.monotonic() - t0
    assert done.returncode == 0, done
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    why = "is not valid TOML (" if bad == "TOML typo" else "nests arrays or tables too deep"
    assert lines[0].startswith(f"rig: {rig_toml} {why}"), lines[0]
    assert "; switching off the devices of the configuration the last run used (" in lines[0]
    assert copy_name(rig_toml) in lines[0]
    assert_all_off(cage)
    assert_read_back_lines(done.stdout)
    print(f"{bad}: rig safe from the last run's copy: last output off {off_after(cage, t0):.2f} s"
          f" after its start, done and read back in {took:.2f} s")  # fmt: skip


def test_an_unparsable_file_without_a_copy_is_one_line(rig_toml: Path) -> None:
    rig_toml.write_text(UNPARSABLE["5000-deep array"](rig_toml.read_text()))
    done, _ = rig_safe(rig_toml)
    assert done.returncode == 2, done
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"rig: error: {rig_toml} nests arrays or tables too deep")
    assert "no run on this computer has used it" in lines[0]
    assert "fix the file and run 'rig safe' again" in lines[0]
    assert "Traceback" not in done.stderr and "RecursionError" not in done.stderr


def test_a_broken_device_table_is_named_and_the_others_go_off(
    cage: SimulatedCage, rig_toml: Path
) -> None:
    drive_everything(rig_toml)
    assert_driven(cage)
    cage.physics.relays.sign = [1, 1, 1]  # the relay reads normal: nothing to switch on it
    text = rig_toml.read_text()
    port = re.search(r"\[devices\.heater\]\n(?:.*\n)*?port = (\d+)", text)
    assert port is not None
    rig_toml.write_text(text.replace(f"port = {port.group(1)}", 'port = "heater"', 1))
    done, _ = rig_safe(rig_toml)
    assert done.returncode == 2, done
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("rig: error: heater: could not confirm off: its [devices.heater]"
                               " table: port must be a whole number, got 'heater'"), lines[0]  # fmt: skip
    supplies = cage.physics.supplies
    assert supplies["heater"].output  # out of reach: where it is cannot be read
    assert not [n for n, s in supplies.items() if s.output and n != "heater"]
    assert re.search(r"^polarity: off \(normal\)$", done.stdout, re.M), done.stdout
    assert "heater:" not in done.stdout


def test_the_copy_is_private_and_a_planted_link_is_not_followed(
    rig_toml: Path, tmp_path: Path
) -> None:
    """The copy is the account's own (0600 in a private lock folder); a link planted where it
    goes is never read as the last configuration (it could name other devices)."""
    with RigSession(load_rig_config(rig_toml), command="test", guardian=False):
        pass
    copy = lock_dir() / copy_name(rig_toml)
    assert copy.stat().st_mode & 0o777 == 0o600
    kept = last_config_copy(rig_toml)
    assert kept is not None and kept[0] == rig_toml.read_text()
    planted = tmp_path / "planted.toml"
    planted.write_text(rig_toml.read_text())
    copy.unlink()
    copy.symlink_to(planted)
    assert last_config_copy(rig_toml) is None
