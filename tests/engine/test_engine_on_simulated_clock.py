"""The engine's pieces on the simulated clock (ADR 0038), without the simulator: the scheduler
reaches its targets exactly in simulated time (a pause shifts them by exactly its length), a
sampler over a line sensor on a simulated wire dates its samples evenly and the same beside CPU
hogs, a silent sensor ends sampling after exactly its timeouts, and a session in simulated time
starts no guardian (saying why) and holds its outputs in this process, not in the lock folder.
Wall times are printed, never asserted."""

from __future__ import annotations

import hashlib
import os
import time
from pathlib import Path

import numpy as np
import pytest

import timebase
from drivers.errors import DeviceTimeoutError
from drivers.mag.ascii_line import AsciiLineMagnetometer
from rig.config import load_rig_config
from rig.engine.interlock import RigBusyError, RigLock, holders, lock_dir
from rig.engine.run_tracker import RunTracker
from rig.engine.sampling import SensorSampler
from rig.engine.schedule import StepScheduler
from rig.engine.session import NO_GUARDIAN_SIMULATED, RigSession
from tests.drivers.wire_devices import Registers, cpu_hogs, serve_tcp
from timebase.wires import wires


class _Rig:
    """What the scheduler asks of its session: a fault check, the events that end a wait and a
    fault-aware sleep."""

    interrupts = ()

    def check(self) -> None:
        pass

    def sleep(self, seconds: float) -> None:
        timebase.sleep(seconds)


def _scheduler(tracker: RunTracker, events: list[tuple[float, str]]) -> StepScheduler:
    def event(level: str, message: str) -> None:
        events.append((timebase.monotonic(), message))

    return StepScheduler(_Rig(), None, tracker, None, {}, 1, event)  # type: ignore[arg-type]


def test_wait_until_reaches_its_target_in_simulated_time_and_a_pause_shifts_it() -> None:
    wall0 = time.monotonic()
    with timebase.simulated(start_s=100.0):
        tracker, events = RunTracker(), []
        sched = _scheduler(tracker, events)
        assert sched.wait_until(3600.0 + 100.0) == 0.0
        assert timebase.monotonic() == pytest.approx(3700.0, abs=1e-9)

        def operator() -> None:  # pauses at 3701 s for 2.5 s
            timebase.sleep(1.0)
            tracker.pause_requested.set()
            timebase.sleep(2.5)
            tracker.pause_requested.clear()

        t = timebase.Thread(operator, name="operator")
        t.start()
        shift = sched.wait_until(3705.0)
        t.join()
        # held from the moment the pause was asked (the wait wakes on it) to the first look
        # after it ended (the hold looks every 50 ms): the pause to within one look
        assert 2.5 - 1e-9 <= shift <= 2.5 + 0.05 + 1e-9
        assert timebase.monotonic() == pytest.approx(3705.0 + shift, abs=1e-9)
        assert [m for _, m in events] == ["paused", "resumed"]
        sim_s = timebase.monotonic() - 100.0
    print(f"wait_until: {sim_s:.3f} s simulated in {time.monotonic() - wall0:.3f} s of wall time")


def _line_sensor(name: str, period_s: float, lines: int, baud: int = 115200) -> None:
    """A self-timed line magnetometer: ``lines`` lines of ``x y z`` (30 bytes each), one every
    ``period_s``."""
    end = wires().serve_serial(name, baud=baud).device

    def run() -> None:
        for k in range(lines):
            timebase.sleep(period_s)
            end.write(f"{k:+09.3f} {2 * k:+09.3f} {-k:+09.3f}\n".encode())

    timebase.Thread(run, name=f"sensor-{name}", daemon=True).start()


def _sample(seconds: float) -> tuple[list[tuple[float, tuple[float, float, float], float]], str]:
    rows: list[tuple[float, tuple[float, float, float], float]] = []
    with timebase.simulated():
        _line_sensor("mag", 0.05, int(seconds / 0.05))
        driver = AsciiLineMagnetometer("simpipe://mag", baudrate=115200, timeout_s=0.5)
        sampler = SensorSampler("mag", driver, lambda t, _d, xyz, unc: rows.append((t, xyz, unc)),
                                rate_hz=20.0)  # fmt: skip
        sampler.start()
        timebase.sleep(seconds + 0.01)
        sampler.stop()
        driver.close()
    digest = hashlib.sha256(repr(rows).encode()).hexdigest()
    return rows, digest


def test_a_sampler_dates_a_line_stream_evenly_and_the_same_beside_cpu_hogs() -> None:
    wall0 = time.monotonic()
    rows, digest = _sample(20.0)
    wall_idle = time.monotonic() - wall0
    assert len(rows) == 400
    dates = np.array([t for t, _, _ in rows])
    assert np.allclose(np.diff(dates), 0.05, atol=1e-9)  # evenly spaced, to the rounding
    # sent at 0.05 s, its last byte in 30 * 10 / 115200 s later: dated when it was sent
    assert dates[0] == pytest.approx(0.05, abs=1e-9)
    assert [xyz for _, xyz, _ in rows[:2]] == [(0.0, 0.0, 0.0), (1.0, 2.0, -1.0)]
    # once the envelope is known (10 arrivals), each date within the stream clock's floor and
    # its early period bound: no scheduling jitter of a busy computer in it
    assert max(unc for _, _, unc in rows[40:]) < 0.0011
    with cpu_hogs(2):
        wall1 = time.monotonic()
        assert _sample(20.0)[1] == digest  # the same record, to the last bit
        wall_hogs = time.monotonic() - wall1
    print(f"20 s of a 20 Hz line stream: {wall_idle:.2f} s of wall time idle,"
          f" {wall_hogs:.2f} s beside two CPU hogs")  # fmt: skip


def test_a_silent_sensor_ends_sampling_after_exactly_two_timeouts() -> None:
    with timebase.simulated():
        wires().serve_serial("quiet", baud=115200)
        driver = AsciiLineMagnetometer("simpipe://quiet", baudrate=115200, timeout_s=0.5)
        warnings: list[tuple[float, str]] = []
        sampler = SensorSampler("quiet", driver, lambda *row: None, rate_hz=20.0,
                                on_warning=lambda m: warnings.append((timebase.monotonic(), m)))  # fmt: skip
        sampler.start()
        while sampler.error is None:
            timebase.sleep(0.01)
        assert isinstance(sampler.error, DeviceTimeoutError)
        assert [t for t, _ in warnings] == [0.5]  # the first timeout is retried, the second ends
        assert timebase.monotonic() == pytest.approx(1.0, abs=0.01)
        sampler.stop()
        driver.close()


RIG_TOML = """
[devices.load_bus]
kind = "regmap-supply"
regmap = "bipolar-supply"
protocol = "modbus-tcp"
host = "127.0.0.1"
port = {port}
max_current_a = 2.0
"""


def test_a_session_in_simulated_time_has_no_guardian_and_locks_in_this_process(
    tmp_path: Path,
) -> None:
    rig_toml = tmp_path / "rig.toml"
    files_before = set(os.listdir(lock_dir())) if lock_dir().exists() else set()
    with timebase.simulated():
        regs = Registers({0x30: 2005})
        port = serve_tcp(regs, port=1502)
        rig_toml.write_text(RIG_TOML.format(port=port))
        cfg = load_rig_config(rig_toml)
        with RigSession(cfg, command="rig test") as rig:
            assert rig.guardian is None and rig.no_guardian == NO_GUARDIAN_SIMULATED
            assert rig.lock is not None and rig.lock.held and not rig.lock.fds
            with pytest.raises(RigBusyError, match=r"load_bus .* in use by 'rig test' .*simulated"):
                RigLock(cfg, "rig other").acquire()
            who = f"'rig test' (PID {os.getpid()}, in simulated time)"
            assert holders(cfg) == {"load_bus": who}
            load = rig.load("load_bus")
            load.set_current(0.5)
            t0 = timebase.monotonic()
            rig.sleep(2.0)
            assert timebase.monotonic() - t0 == pytest.approx(2.0)
        assert rig.read_back is not None and rig.read_back["load_bus"].off
        assert not holders(cfg)
        with RigLock(cfg, "rig again"):  # released: the next command may take it
            pass
    assert not holders(cfg)  # the wall clock's lock folder never saw any of it
    after = set(os.listdir(lock_dir())) if lock_dir().exists() else set()
    assert after == files_before
