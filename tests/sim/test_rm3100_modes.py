"""RM3100 mode bits as the PNI RM3100 user manual gives them (Tables 5-2 to 5-5): DRDY in
continuous mode follows DRDM (00: ALARM and the chosen axes done; 01: after any axis; 10: after
the chosen axes; 11: ALARM), ALARM follows the alarm limits (power-on 0: any nonzero reading),
CMX/CMY/CMZ and PMX/PMY/PMZ choose the axes measured, and the self test (BIST) reads back its
axes' OK bits. The driver runs against the simulated sensor on its smbus2-compatible bus."""

from __future__ import annotations

import time

import numpy as np
import pytest

import drivers.mag.rm3100 as rm3100_driver
import timebase
from drivers.mag.rm3100 import Rm3100
from sim.i2c_bus import SimI2CBus
from sim.physics import Faults
from sim.rm3100 import Rm3100 as SimRm3100

pytestmark = pytest.mark.realtime

FIELD_UT = (12.5, -20.0, 31.0)
GAIN = 0.3671 * 200 + 1.5  # counts per uT at the default cycle count


def sim_bus() -> tuple[SimI2CBus, SimRm3100]:
    bus = SimI2CBus()
    device = SimRm3100(lambda _t: np.array(FIELD_UT), Faults())
    bus.attach(device)
    return bus, device


def drdy(bus: SimI2CBus) -> bool:
    return bool(bus.read_byte_data(0x20, 0x34) & 0x80)


def results(bus: SimI2CBus) -> list[int]:
    raw = bytes(bus.read_i2c_block_data(0x20, 0x24, 9))
    return [int.from_bytes(raw[i : i + 3], "big", signed=True) for i in (0, 3, 6)]


def wait_drdy(bus: SimI2CBus, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if drdy(bus):
            return True
        time.sleep(0.002)
    return False


def test_driver_continuous_mode_gets_drdy_after_every_measurement() -> None:
    bus, _ = sim_bus()
    rm = Rm3100(bus, 0x20, cycle_count=200)
    assert rm.start_continuous(0x94) == 150.0
    for _ in range(5):
        assert rm.read(timeout_s=0.5) == pytest.approx(FIELD_UT, abs=0.02)
    rm.stop_continuous()


def test_a_driver_writing_0x71_sees_drdy_while_the_alarm_limits_are_at_power_on_zero(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """DRDM = 00 raises DRDY when ALARM is 1 and the sequence is done (Table 5-3); with both
    limits at their power-on 0 any nonzero reading is an alarm (5.2.2), so a driver writing 0x71,
    as ArduPilot's and Firmament's do, reads every set. Before, the simulator never raised it."""
    monkeypatch.setattr(rm3100_driver, "CMM_CONTINUOUS", 0x71)
    with timebase.simulated():
        bus, _ = sim_bus()
        rm = Rm3100(bus, 0x20, cycle_count=200)
        rm.start_continuous(0x94)
        for _ in range(3):
            assert rm.read(timeout_s=0.1) == pytest.approx(FIELD_UT, abs=0.02)


ABOVE_THE_FIELD = list(b"\x00\x00\x00" + (100_000).to_bytes(3, "big")) * 3
"""ALL = 0 and AUL = 100 000 counts on every axis: the field of FIELD_UT_POSITIVE is inside."""
FIELD_UT_POSITIVE = (12.5, 20.0, 31.0)


@pytest.mark.parametrize(
    ("cmm", "limits_around_the_field", "raised"),
    [(0x71, False, True), (0x71, True, False), (0x75, True, True), (0x79, True, True),
     (0x7D, False, True), (0x7D, True, False)],
)  # fmt: skip
def test_drdm_and_the_alarm_limits_decide_drdy_in_continuous_mode(
    cmm: int, limits_around_the_field: bool, raised: bool
) -> None:
    with timebase.simulated():
        bus = SimI2CBus()
        bus.attach(SimRm3100(lambda _t: np.array(FIELD_UT_POSITIVE), Faults()))
        if limits_around_the_field:
            bus.write_i2c_block_data(0x20, 0x0C, ABOVE_THE_FIELD)
        bus.write_byte_data(0x20, 0x0B, 0x92)  # TMRC: the fastest rate
        bus.write_byte_data(0x20, 0x01, cmm)
        timebase.sleep(0.05)
        assert drdy(bus) is raised
        # the results update whatever DRDY says; reading CMM (which ends continuous mode) shows
        # ALARM, bit 1
        assert results(bus) == [round(v * GAIN) for v in FIELD_UT_POSITIVE]
        assert bool(bus.read_byte_data(0x20, 0x01) & 0x02) is not limits_around_the_field


def test_the_self_test_reads_back_the_ok_bits_of_the_axes_it_tested() -> None:
    """BIST with STE set, then a POLL: DRDY at its end, and a healthy part's XOK/YOK/ZOK read 1
    for the polled axes (manual 5.6.1); the results are not touched. Before, BIST read back as
    written, with no OK bits."""
    with timebase.simulated():
        bus, _ = sim_bus()
        bus.write_byte_data(0x20, 0x33, 0x8F)  # STE, BW = 11 (120 us), BP = 11 (4 LR periods)
        bus.write_byte_data(0x20, 0x00, 0x70)  # POLL x, y, z: the self test
        timebase.sleep(0.01)
        assert drdy(bus) and bus.read_byte_data(0x20, 0x33) == 0xFF
        assert results(bus) == [0, 0, 0]
        bus.write_byte_data(0x20, 0x33, 0x8F)  # a new test clears the OK bits
        bus.write_byte_data(0x20, 0x00, 0x30)  # x and y only
        timebase.sleep(0.01)
        assert bus.read_byte_data(0x20, 0x33) == 0x8F | 0x30
        bus.write_byte_data(0x20, 0x33, 0x00)  # STE off: a POLL measures again
        bus.write_byte_data(0x20, 0x00, 0x70)
        timebase.sleep(0.01)
        assert drdy(bus) and results(bus) == [round(v * GAIN) for v in FIELD_UT]


def test_only_the_chosen_axes_are_measured() -> None:
    bus, _ = sim_bus()
    bus.write_byte_data(0x20, 0x00, 0x10)  # POLL: PMX only
    assert wait_drdy(bus, 0.3)
    x, y, z = results(bus)
    assert x == round(FIELD_UT[0] * GAIN) and (y, z) == (0, 0)
    bus.write_byte_data(0x20, 0x0B, 0x92)
    bus.write_byte_data(0x20, 0x01, 0x49)  # CMM: START, DRDM = 10, CMZ only
    assert wait_drdy(bus, 0.3)
    x2, y2, z2 = results(bus)
    assert (x2, y2) == (x, 0) and z2 == round(FIELD_UT[2] * GAIN)


def test_each_axis_reads_the_field_at_the_middle_of_its_own_conversion() -> None:
    """The axes convert one after another, each for its cycle count: the field each one latches
    is the field at the middle of its own conversion (x, then y, then z; at CC = 200, 0.78 ms
    apart), the truth a frequency response of the sensor sees as a lag per axis."""
    from sim.rm3100 import SECONDS_PER_CYCLE

    asked: list[float] = []

    def field(t: float) -> np.ndarray:
        asked.append(t)
        return np.array(FIELD_UT)

    bus = SimI2CBus()
    device = SimRm3100(field, Faults())
    bus.attach(device)
    bus.write_i2c_block_data(0x20, 0x06, [0, 100])  # CCY = 100
    t0 = time.monotonic()
    bus.write_byte_data(0x20, 0x00, 0x70)  # POLL x, y, z
    assert wait_drdy(bus, 1.0)
    done = t0 + (200 + 100 + 200) * SECONDS_PER_CYCLE
    step = SECONDS_PER_CYCLE
    want = [done - 500 * step + 100 * step, done - 300 * step + 50 * step, done - 100 * step]
    assert len(asked) == 3 and np.allclose(asked, want, atol=2e-4), (asked, want)
    assert results(bus) == [round(FIELD_UT[0] * GAIN), round(FIELD_UT[1] * (0.3671 * 100 + 1.5)),
                            round(FIELD_UT[2] * GAIN)]  # fmt: skip
