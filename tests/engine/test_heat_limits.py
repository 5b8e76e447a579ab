"""Heaters and the DUT's temperature are bounded (issue 51, ADR 0035): an output's ``max_power_w``
refuses a set-point whose worst case |I| x V exceeds it; ``rig check`` and ``rig run`` refuse a
heater plan beyond a load's current or power limit or predicted beyond the DUT thermometer's
``max_temperature_c``; and during a run that thermometer is an interlock: on the simulated cage
over real Modbus, the heater is off within 1 s of the DUT's true temperature crossing the limit."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from drivers.errors import DeviceError
from drivers.protocols import SupplyReading
from rig.config import load_rig_config
from rig.engine.health import HealthMonitor
from rig.engine.runner import Runner
from rig.engine.temperature_log import STALE_S, Interlock, TemperatureLog
from rig.errors import UserInputError
from rig.output_limits import LimitedOutput, OutputLimitError, OutputLimits
from rig.procedure.heat_limits import heater_refusals
from rig.procedure.language import parse_procedure
from sim.cage import SimulatedCage
from sim.config import load_config
from tests.simcage import write_rig_toml
from tests.simrun import run_watched

RIG = [sys.executable, "-m", "rig.cli"]
pytestmark = [pytest.mark.realtime, pytest.mark.usefixtures("own_lock_dir")]

SIM_TAU_S = 10.0
"""The simulated mount's time constant in this module (s): 2 A (16 W, 2 K/W) warms it 3 K in
about 1 s, while the rig configuration states the default cage's 120 s."""


@pytest.fixture(scope="module")
def cage() -> Iterator[SimulatedCage]:
    """The default cage with a quick thermal mass (``SIM_TAU_S``)."""
    cfg = load_config()
    assert cfg.thermal is not None
    with SimulatedCage(replace(cfg, thermal=replace(cfg.thermal, tau_s=SIM_TAU_S))) as sim:
        yield sim


def heater_procedure(amps: float, seconds: float = 6.0) -> str:
    """A sphere sweep of ``seconds`` with the heater at ``amps`` throughout."""
    dirs = 8
    return f"""procedure: Heater
magnetometers: {{dut: dut, reference: reference}}
loads: [heater]
steps:
  - sphere_sweep: {{directions: {dirs}, magnitude_ut: [20, 30], dwell_s: {seconds / dirs:g}}}
    name: warming
    loads:
      heater: {{constant: {{current_a: {amps:g}}}}}
"""


def edited(rig_toml: Path, device: str, **keys: Any) -> Path:
    """``rig_toml`` with ``keys`` of ``[devices.<device>]`` set (replaced or added)."""
    out, inside = [], False
    for line in rig_toml.read_text().splitlines():
        if line.startswith("["):
            inside = line == f"[devices.{device}]"
        elif inside and line.split(" = ")[0] in keys:
            continue
        out.append(line)
        if inside and line.startswith("["):
            out += [f"{k} = {v!r}".replace("'", '"') for k, v in keys.items()]
    path = rig_toml.with_name(f"{rig_toml.stem}-{device}.toml")
    path.write_text("\n".join(out) + "\n")
    return path


# --- the power limit where it is written -------------------------------------------------------


class FakeSupply:
    """A supply driver that records what reaches it."""

    name = "heater"
    max_current_a = 6.0
    max_voltage_v = 60.0

    def __init__(self, sets_voltage: bool = True) -> None:
        self.sent: list[tuple[str, float]] = []
        self.sets_voltage = sets_voltage

    def set_current(self, amps: float) -> float:
        self.sent.append(("A", amps))
        return amps

    def set_voltage(self, volts: float) -> float:
        self.sent.append(("V", volts))
        return volts

    def enable_as_load(self, compliance_v: float) -> None:
        self.sent.append(("load", compliance_v))

    def safe(self) -> None:
        self.sent.append(("safe", 0.0))


def limited(driver: FakeSupply, max_voltage_v: float | None = None) -> LimitedOutput:
    return LimitedOutput(driver, OutputLimits("heater", 6.0, "the instrument's range",
                                              max_voltage_v, "max_voltage_v", 20.0,
                                              "max_power_w of [devices.heater]"))  # fmt: skip


def test_a_current_whose_worst_case_power_exceeds_max_power_w_is_refused_and_not_sent() -> None:
    drv = FakeSupply()
    out = limited(drv)
    out.enable_as_load(30.0)  # the issue's compliance: 6 A x 30 V = 180 W
    drv.sent.clear()
    assert out.set_current(0.6) == 0.6  # 18 W
    assert out.set_current(2 / 3) == pytest.approx(2 / 3)  # 20 W: at the limit
    with pytest.raises(OutputLimitError) as err:
        out.set_current(6.0)
    message = str(err.value)
    assert "\n" not in message
    assert "6 A x 30 V = 180 W, beyond its 20 W limit (max_power_w of [devices.heater])" in message
    assert "nothing was sent: at 30 V ask at most 0.667 A" in message
    with pytest.raises(OutputLimitError):
        out.set_current(-6.0)  # the magnitude counts
    with pytest.raises(OutputLimitError):
        out.set_current(math.nan)
    assert drv.sent == [("A", 0.6), ("A", pytest.approx(2 / 3))]


def test_a_voltage_that_would_raise_the_worst_case_beyond_the_limit_is_refused() -> None:
    drv = FakeSupply()
    out = limited(drv)
    out.set_voltage(10.0)
    out.set_current(2.0)  # 20 W
    with pytest.raises(OutputLimitError, match="a set-point of 12 V at 2 A makes a worst case"):
        out.set_voltage(12.0)
    assert out.set_voltage(5.0) == 5.0
    assert out.set_current(4.0) == 4.0  # 4 A x 5 V
    assert drv.sent == [("V", 10.0), ("A", 2.0), ("V", 5.0), ("A", 4.0)]


def test_before_any_voltage_and_on_an_electronic_load_the_voltage_limit_is_the_worst_case() -> None:
    out = limited(FakeSupply(), max_voltage_v=40.0)
    with pytest.raises(OutputLimitError, match=r"0.6 A x 40 V = 24 W"):
        out.set_current(0.6)  # no voltage set-point yet: it may reach its 40 V limit
    out.set_current(0.5)
    eload = limited(FakeSupply(sets_voltage=False), max_voltage_v=40.0)
    eload.enable_as_load(5.0)  # no voltage set-point: the source decides, up to 40 V
    with pytest.raises(OutputLimitError, match=r"1 A x 40 V = 40 W"):
        eload.set_current(1.0)


# --- the dry run: current, power, predicted temperature -----------------------------------------

RIG_TOML = """
[devices.heater]
kind = "riden-rd60xx"
protocol = "modbus-tcp"
host = "127.0.0.1"
port = 5020
compliance_v = {compliance}
max_power_w = 20.0
heats = "dut_temp"
kelvin_per_w = 2.0
resistance_ohm = 4.0
{tau}

[devices.dut_temp]
kind = "regmap-thermometer"
protocol = "modbus-tcp"
host = "127.0.0.1"
port = 5021
regmap = "rtd-module"
max_temperature_c = {limit}
"""


def refusals(tmp_path: Path, amps: float, seconds: float, compliance: float = 10.0,
             limit: float = 70.0, tau: float | None = 120.0) -> list[str]:  # fmt: skip
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG_TOML.format(compliance=compliance, limit=limit,
                                   tau="" if tau is None else f"thermal_tau_s = {tau}"))  # fmt: skip
    proc = tmp_path / "p.yaml"
    proc.write_text(heater_procedure(amps, seconds))
    return heater_refusals(parse_procedure(proc), load_rig_config(rig))


def test_the_prediction_is_first_order_over_the_plan_and_steady_state_without_tau(
    tmp_path: Path,
) -> None:
    # 2 A into 4 ohm: 16 W, +32 K at steady state; 192 s of a 120 s mount: +25.5 K
    rise = 32.0 * (1.0 - math.exp(-192.0 / 120.0))
    assert refusals(tmp_path, 2.0, 192.0, limit=25.0 + rise + 0.05) == []
    (too_hot,) = refusals(tmp_path, 2.0, 192.0, limit=25.0 + rise - 0.05)
    assert f"to {25.0 + rise:.1f} C" in too_hot, too_hot
    assert (
        "load heater at 2 A is predicted to warm dut_temp beyond its max_temperature_c" in too_hot
    )
    assert "step 1 (warming)" in too_hot and "hold heater at most" in too_hot
    # without a time constant the steady state counts at once: 57 C
    assert refusals(tmp_path, 2.0, 6.0, limit=56.9, tau=None) != []
    assert refusals(tmp_path, 2.0, 6.0, limit=57.1, tau=None) == []


def test_the_dry_run_refuses_current_power_and_sign(tmp_path: Path) -> None:
    (power,) = refusals(tmp_path, 2.5, 6.0)  # 25 W worst case, 25 W into 4 ohm
    assert "load heater at 2.5 A may deliver 25 W (worst case 2.5 A x 10 V" in power
    assert "beyond its max_power_w of 20 W: ask at most 2 A" in power
    (current,) = [r for r in refusals(tmp_path, 40.0, 6.0) if "30 A limit" in r]
    assert "load heater at 40 A is beyond its 30 A limit (the largest range of any" in current
    negative = refusals(tmp_path, -1.0, 6.0)
    assert len(negative) == 1 and "drives current one way only (a riden-rd60xx)" in negative[0]


def test_a_heats_that_names_no_thermometer_is_refused(tmp_path: Path) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG_TOML.format(compliance=10, limit=70, tau="")
                   .replace('heats = "dut_temp"', 'heats = "dut_tmp"'))  # fmt: skip
    proc = tmp_path / "p.yaml"
    proc.write_text(heater_procedure(1.0))
    (problem,) = heater_refusals(parse_procedure(proc), load_rig_config(rig))
    assert 'heats = "dut_tmp" names no thermometer of the rig: name one of dut_temp' in problem


def test_rig_check_refuses_the_issues_heater_with_one_limit_line_per_problem(
    rig_toml: Path, tmp_path: Path
) -> None:
    """The issue's attack: a 6 A heater with compliance_v = 30 (144 W into 4 ohm, 313 C at
    steady state) passed ``rig check`` with a note; now: exit 1, a LIMIT line for its power and
    one for the DUT's predicted temperature."""
    attack = edited(rig_toml, "heater", compliance_v=30.0)
    proc = tmp_path / "hot.yaml"
    proc.write_text(heater_procedure(6.0, 90.0))
    done = subprocess.run([*RIG, "check", str(proc), "--rig", str(attack)], capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert done.returncode == 1, done
    limits = [line for line in done.stdout.splitlines() if line.startswith("LIMIT:")]
    assert len(limits) == 2, done.stdout
    assert "6 A x 30 V, its compliance_v), beyond its max_power_w of 20 W" in limits[0]
    assert "warm dut_temp beyond its max_temperature_c of 70 C" in limits[1]
    # 40 A and -5 A on the heater: refused too (the run used to find out 9.8 s in)
    for amps, words in ((40.0, "beyond its 30 A limit"), (-5.0, "one way only")):
        proc.write_text(heater_procedure(amps))
        done = subprocess.run([*RIG, "check", str(proc), "--rig", str(rig_toml)],
                              capture_output=True, text=True, timeout=120)  # fmt: skip
        assert done.returncode == 1 and words in done.stdout, done.stdout


def test_rig_run_refuses_the_heater_before_any_output_is_written(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path
) -> None:
    attack = edited(rig_toml, "heater", compliance_v=30.0)
    proc = tmp_path / "hot.yaml"
    proc.write_text(heater_procedure(6.0, 90.0))
    writes = {n: s.writes for n, s in cage.physics.supplies.items()}
    runs = tmp_path / "runs"
    runner = Runner(parse_procedure(proc), load_rig_config(attack), runs, i2c_bus=cage.i2c_bus,
                    confirm=lambda s: True, live=False)  # fmt: skip
    with pytest.raises(UserInputError, match="beyond its max_power_w of 20 W"):
        runner.run()
    assert not runs.exists()
    assert {n: s.writes for n, s in cage.physics.supplies.items()} == writes
    done = subprocess.run([*RIG, "run", str(proc), "--rig", str(attack), "--yes", "--runs-dir",
                           str(runs)], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "max_power_w" in done.stderr
    assert not runs.exists()
    assert {n: s.writes for n, s in cage.physics.supplies.items()} == writes


# --- the run: read-back power, the thermometer as interlock -------------------------------------


class Faults:
    def __init__(self) -> None:
        self.faults: list[str] = []

    def fail(self, message: str) -> None:
        self.faults.append(message)


def test_a_read_back_power_beyond_max_power_w_is_a_fault() -> None:
    rig = Faults()
    monitor = HealthMonitor.__new__(HealthMonitor)
    monitor.rig = rig  # type: ignore[assignment]
    load = limited(FakeSupply())
    monitor._check_power("heater", load, 10.0, 2.0)  # 20 W: at the limit
    monitor._check_power("heater", load, 10.1, 2.05)  # 20.7 W: within the read-back's tolerance
    assert rig.faults == []
    monitor._check_power("heater", load, 24.0, 6.0)
    (fault,) = rig.faults
    assert fault.startswith("heater: it delivers 144.0 W (24.00 V x 6.000 A read back), beyond"
                            " its 20 W max_power_w")  # fmt: skip
    reading = SupplyReading(24.0, 6.0, 24.0, 6.0, True, True, "")
    assert reading.v_out_v * reading.i_out_a == 144.0


class FakeThermometer:
    def __init__(self, readings: list[float | None]) -> None:
        self.readings = readings

    def read_temperature_c(self) -> float:
        value = self.readings.pop(0) if len(self.readings) > 1 else self.readings[0]
        if value is None:
            time.sleep(0.05)
            raise DeviceError("dut_temp: no reply")
        return value


def test_a_reading_beyond_the_limit_is_a_fault_naming_the_thermometer_reading_and_limit() -> None:
    rig = Faults()
    log = TemperatureLog("dut_temp", FakeThermometer([26.0, 27.9, 28.4]),  # type: ignore[arg-type]
                         lambda *a: None, lambda *a: None, period_s=0.01,
                         interlock=Interlock(28.0, rig.fail, lambda: []))  # fmt: skip
    log.start()
    time.sleep(0.2)
    log.stop()
    assert rig.faults, "the reading of 28.4 C went unnoticed"
    assert rig.faults[0].startswith("dut_temp reads 28.4 C, beyond its max_temperature_c of 28 C;"
                                    " outputs switched off: let the DUT cool")  # fmt: skip


@pytest.mark.parametrize("heating", [True, False])
def test_a_silent_interlock_thermometer_is_a_fault_only_while_its_heater_is_driven(
    heating: bool,
) -> None:
    rig = Faults()
    log = TemperatureLog("dut_temp", FakeThermometer([25.0, None]),  # type: ignore[arg-type]
                         lambda *a: None, lambda *a: None, period_s=0.05,
                         interlock=Interlock(70.0, rig.fail,
                                             lambda: ["heater"] if heating else []))  # fmt: skip
    log.start()
    time.sleep(STALE_S + 0.6)
    log.stop()
    if heating:
        assert len(rig.faults) == 1 and rig.faults[0].startswith("dut_temp has given no"
                                                                 " temperature for 2.")  # fmt: skip
        assert "while heater heats the DUT" in rig.faults[0]
    else:
        assert rig.faults == []


def test_the_dut_over_its_limit_is_taken_safe_within_a_second_on_the_simulated_cage(
    cage: SimulatedCage, tmp_path: Path
) -> None:
    """The DUT's limit 3 K above the simulated 25 C; the heater at 2 A (16 W; the rig's stated
    120 s mount predicts +1.6 K in the 6 s step, so ``rig run`` lets it start, but this mount's
    true time constant is 10 s): the run ends ``error`` naming dut_temp, and the heater is off
    within 1 s of the simulated DUT's true temperature crossing 28 C (watched every 1 ms)."""
    rig_toml = edited(write_rig_toml(cage, tmp_path), "dut_temp", max_temperature_c=28.0)
    proc = tmp_path / "p.yaml"
    proc.write_text(heater_procedure(2.0, 6.0))
    heater, physics = cage.physics.supplies["heater"], cage.physics
    while physics.dut_temperature_c() > 25.05:  # an earlier test's warming
        time.sleep(0.1)
    crossed: list[float] = []
    peak = [0.0]

    def watch(t: float) -> None:
        temperature = physics.dut_temperature_c(t)
        peak[0] = max(peak[0], temperature)
        if temperature > 28.0 and not crossed:
            crossed.append(t)

    outcome = run_watched(cage, rig_toml, proc, tmp_path / "runs", watch, period_s=0.001)
    assert outcome.status == "error", outcome.reason
    assert outcome.reason.startswith("dut_temp reads 28."), outcome.reason
    assert "beyond its max_temperature_c of 28 C" in outcome.reason
    assert crossed, f"the DUT never passed 28 C (peak {peak[0]:.2f} C)"
    assert heater.off_since_s is not None and not heater.output
    to_off_s = heater.off_since_s - crossed[0]
    print(f"limit crossed -> heater off: {to_off_s * 1e3:.0f} ms; peak {peak[0]:.2f} C")
    assert 0.0 < to_off_s < 1.0, to_off_s
    assert peak[0] < 28.0 + 1.0  # 5.3 K/s at most at 2 A: under 1 s, under 1 K beyond


def test_an_interlock_thermometer_that_goes_silent_while_the_heater_is_on_ends_the_run(
    cage: SimulatedCage, tmp_path: Path
) -> None:
    """dut_temp stops answering half a second after the heater (1 A) is on: the run ends
    ``error`` naming it and the heater, the heater off about STALE_S after its last reading."""
    rig_toml = write_rig_toml(cage, tmp_path)
    proc = tmp_path / "p.yaml"
    proc.write_text(heater_procedure(1.0, 8.0))
    heater = cage.physics.supplies["heater"]
    silenced: list[float] = []
    stop = threading.Event()

    def silence_once_heating() -> None:
        while not stop.wait(0.005):
            if heater.output and heater.i_set > 0.5:
                time.sleep(0.5)
                cage.faults["dut_temp"].silent = True
                silenced.append(time.monotonic())
                return

    silencer = threading.Thread(target=silence_once_heating, daemon=True)
    silencer.start()
    try:
        outcome = Runner(parse_procedure(proc), load_rig_config(rig_toml), tmp_path / "runs",
                         i2c_bus=cage.i2c_bus, confirm=lambda s: True, live=False).run()  # fmt: skip
    finally:
        stop.set()
        silencer.join(1.0)
        cage.faults["dut_temp"].silent = False
    assert silenced, "the heater never came on"
    assert outcome.status == "error", outcome.reason
    assert outcome.reason.startswith("dut_temp has given no temperature for 2."), outcome.reason
    assert "while heater heats the DUT" in outcome.reason
    assert heater.off_since_s is not None and not heater.output
    off_after_s = heater.off_since_s - silenced[0]
    print(f"thermometer silent -> heater off: {off_after_s:.2f} s")
    # STALE_S from the last reading, which came up to one period (0.25 s) before the silence
    assert STALE_S - 0.3 < off_after_s < STALE_S + 1.0, off_after_s
