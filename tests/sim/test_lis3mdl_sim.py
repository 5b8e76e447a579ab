"""The simulated LIS3MDL (sim/lis3mdl.py, one module and one line in sim/device_kinds.py) read
through the project's driver (drivers/mag/lis3mdl.py) over the simulated I2C bus."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator

import numpy as np
import pytest
from smbus2 import i2c_msg

import timebase
from drivers.errors import DeviceError
from drivers.mag.lis3mdl import Lis3mdl
from sim.cage import SimulatedCage
from sim.config import EndpointConfig, MagnetometerConfig, load_config
from sim.i2c_bus import SimI2CBus
from sim.lis3mdl import CTRL_REG1, CTRL_REG3, OUT_X_L, STATUS, ZYXDA, ZYXOR
from sim.lis3mdl import Lis3mdl as SimLis3mdl
from sim.physics import Faults

pytestmark = pytest.mark.realtime


def _lis3mdl(**kw: object) -> MagnetometerConfig:
    return MagnetometerConfig(name="lis", kind="lis3mdl", endpoint=EndpointConfig("i2c"),
                              i2c_address=0x1E, scale=(1.01, 0.99, 1.02),
                              offset_ut=(4.0, -2.5, 1.5), noise_ut=0.05, **kw)  # type: ignore[arg-type]  # fmt: skip


@pytest.fixture(scope="module")
def cage() -> Iterator[SimulatedCage]:
    cfg = load_config()
    cfg = dataclasses.replace(cfg, magnetometers=(*cfg.magnetometers, _lis3mdl()))
    c = SimulatedCage(cfg)
    c.start()
    yield c
    c.stop()


def _truth(cage: SimulatedCage) -> np.ndarray:
    mag = cage.physics.magnetometers["lis"]
    return mag.truth_reading(cage.physics.field_ut(noise=False),
                             cage.physics.load_currents(time.monotonic(), mag.cfg.delay_s))  # fmt: skip


def test_the_driver_reads_the_truth_at_every_full_scale(cage: SimulatedCage) -> None:
    assert cage.endpoints_document()["devices"]["lis"] == {
        "kind": "lis3mdl", "protocol": "i2c", "bus": "sim", "address": 0x1E}  # fmt: skip
    for fs in (4, 16):
        lis = Lis3mdl(cage.i2c_bus, 0x1E, full_scale_gauss=fs)
        t0 = time.monotonic()
        readings = np.array([lis.read() for _ in range(16)])
        elapsed = time.monotonic() - t0
        # 16 new sets at 80 Hz take about 0.2 s (each read waits for ZYXDA)
        assert 0.15 < elapsed < 2.0, elapsed
        lsb_ut = 100.0 / {4: 6842.0, 16: 1711.0}[fs]
        assert np.all(np.abs(readings.mean(axis=0) - _truth(cage)) < 0.05 + lsb_ut)
        assert np.all(readings.std(axis=0) < 0.2)
        lis.safe()  # power-down: no new set arrives
        with pytest.raises(DeviceError):
            # a set completed before the power-down may still wait to be read (a busy computer
            # reaches safe() more than one 12.5 ms period after the last read): one, not more
            for _ in range(2):
                lis.read(timeout_s=0.1)


def test_status_bits_overrun_and_wrong_device(cage: SimulatedCage) -> None:
    dev = cage.i2c_devices["lis"]
    Lis3mdl(cage.i2c_bus, 0x1E)  # continuous at 80 Hz
    time.sleep(0.1)
    status = cage.i2c_bus.read_byte_data(0x1E, STATUS)
    assert status & ZYXDA and status & ZYXOR  # several sets since: the older ones overwritten
    cage.i2c_bus.read_i2c_block_data(0x1E, 0x28 | 0x80, 6)
    assert cage.i2c_bus.read_byte_data(0x1E, STATUS) & (ZYXDA | ZYXOR) == 0
    assert cage.i2c_bus.read_i2c_block_data(0x1E, 0x0F, 2) == [0x3D, 0x3D]  # no auto-increment
    assert dev.odr_hz() == 80.0
    with pytest.raises(DeviceError):
        Lis3mdl(cage.i2c_bus, 0x1C)  # nobody there
    cage.faults["lis"].silent = True
    try:
        with pytest.raises(DeviceError):
            Lis3mdl(cage.i2c_bus, 0x1E)
    finally:
        cage.faults["lis"].silent = False


def test_a_lis3mdl_at_an_address_it_cannot_take_is_refused() -> None:
    cfg = load_config()
    bad = dataclasses.replace(_lis3mdl(), i2c_address=0x20)
    cage = SimulatedCage(dataclasses.replace(cfg, magnetometers=(*cfg.magnetometers[:2], bad)))
    with pytest.raises(ValueError, match="0x1C or 0x1E, not 0x20"):
        cage.start()


TRUE_UT = (12.34, -45.67, 78.9)


def _bus_in_continuous_mode() -> SimI2CBus:
    """A simulated LIS3MDL at 0x1E on its own bus, +-4 G, in continuous mode for 0.2 s (two
    conversions at the power-on 10 Hz), reading ``TRUE_UT``."""
    bus = SimI2CBus()
    bus.attach(SimLis3mdl(lambda _t: np.array(TRUE_UT), Faults(), 0x1E))
    bus.write_byte_data(0x1E, CTRL_REG3, 0x00)
    timebase.sleep(0.2)
    return bus


def _read(bus: SimI2CBus, sub: int, n: int) -> bytes:
    """What a library reads: the sub-address written, then ``n`` bytes in one combined transfer."""
    write, read = i2c_msg.write(0x1E, [sub]), i2c_msg.read(0x1E, n)
    bus.i2c_rdwr(write, read)
    return bytes(read)


def _ut(raw: bytes) -> tuple[float, ...]:
    return tuple(int.from_bytes(raw[i : i + 2], "little", signed=True) / 68.42 for i in (0, 2, 4))


def test_the_output_registers_auto_increment_without_the_sub_address_msb() -> None:
    """A six-byte read from OUT_X_L without bit 7 of the sub-address gets X, Y and Z, as real
    parts give it to the libraries that read so (Adafruit's, PX4's I2C driver: a logic-analyzer
    trace in PX4 issue 12514); before, it got OUT_X_L six times: (285.47, 285.47, 285.47) uT."""
    with timebase.simulated():
        bus = _bus_in_continuous_mode()
        assert _ut(_read(bus, OUT_X_L, 6)) == pytest.approx(TRUE_UT, abs=100 / 6842)
        with_msb = _read(bus, OUT_X_L | 0x80, 6)
        assert _read(bus, OUT_X_L, 6) == with_msb


def test_a_read_past_out_z_h_wraps_to_out_x_l_and_other_registers_follow_the_datasheet() -> None:
    """Past OUT_Z_H (0x2D) the pointer goes back to OUT_X_L (PX4 issue 12514's trace; ST's
    community answer: "standard behavior"); outside the output registers a read without bit 7
    stays on its register (DocID024204, 5.1.1)."""
    with timebase.simulated():
        bus = _bus_in_continuous_mode()
        eight = _read(bus, OUT_X_L | 0x80, 8)
        assert eight[6:] == eight[:2] and _read(bus, OUT_X_L, 8) == eight
        assert _read(bus, CTRL_REG1, 2) == bytes([0x10, 0x10])  # DO = 10 Hz, twice
        assert _read(bus, CTRL_REG1 | 0x80, 2) == bytes([0x10, 0x00])  # CTRL_REG1, CTRL_REG2
