"""The simulated LIS3MDL (sim/lis3mdl.py, one module and one line in sim/device_kinds.py) read
through the project's driver (drivers/mag/lis3mdl.py) over the simulated I2C bus."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.errors import DeviceError
from drivers.mag.lis3mdl import Lis3mdl
from sim.cage import SimulatedCage
from sim.config import EndpointConfig, MagnetometerConfig, load_config
from sim.lis3mdl import STATUS, ZYXDA, ZYXOR


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
