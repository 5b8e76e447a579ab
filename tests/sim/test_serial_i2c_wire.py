"""The ASCII reference magnetometer (pyserial) and the RM3100 (smbus2 messages) on their wires."""

from __future__ import annotations

import errno
import time
from typing import Any

import numpy as np
import pytest
import serial
from smbus2 import i2c_msg

from sim.cage import SimulatedCage
from sim.rm3100 import SECONDS_PER_CYCLE

pytestmark = pytest.mark.realtime


def test_ascii_reference_streams_lines_in_microtesla(
    devices: dict[str, Any], cage: SimulatedCage
) -> None:
    dev = devices["reference"]
    with serial.Serial(dev["path"], dev["baudrate"], timeout=1.0) as s:
        s.reset_input_buffer()
        s.readline()  # possibly partial
        t0 = time.monotonic()
        lines = [s.readline() for _ in range(10)]
        elapsed = time.monotonic() - t0
    values = np.array([[float(v) for v in ln.split()] for ln in lines])
    assert values.shape == (10, 3)
    truth = cage.physics.magnetometers["reference"].truth_reading(
        cage.physics.field_ut(noise=False), {}
    )
    assert np.all(np.abs(values.mean(axis=0) - truth) < 0.05)
    assert 0.3 < elapsed < 0.8  # 20 lines per second


def _read(bus: Any, addr: int, reg: int, n: int) -> bytes:
    w, r = i2c_msg.write(addr, [reg]), i2c_msg.read(addr, n)
    bus.i2c_rdwr(w, r)
    return bytes(r)


def _write(bus: Any, addr: int, reg: int, data: list[int]) -> None:
    bus.i2c_rdwr(i2c_msg.write(addr, [reg, *data]))


def test_rm3100_poll_drdy_and_24_bit_results(cage: SimulatedCage) -> None:
    bus = cage.i2c_bus
    assert _read(bus, 0x20, 0x36, 1) == b"\x22"  # REVID, plain address over I2C
    _write(bus, 0x20, 0x04, [0x00, 0x64, 0x00, 0x64, 0x00, 0x64])  # CC = 100 on all axes
    assert _read(bus, 0x20, 0x04, 6) == bytes([0, 100] * 3)
    conversion_s = 3 * 100 * SECONDS_PER_CYCLE
    t_poll = time.monotonic()
    _write(bus, 0x20, 0x00, [0x70])  # POLL x, y, z
    status = _read(bus, 0x20, 0x34, 1)[0]
    if time.monotonic() - t_poll < conversion_s:  # (not if this test was descheduled meanwhile)
        assert status & 0x80 == 0  # conversion takes time
    deadline = time.monotonic() + 1.0
    while not _read(bus, 0x20, 0x34, 1)[0] & 0x80:
        assert time.monotonic() < deadline
    raw = _read(bus, 0x20, 0x24, 9)
    counts = [int.from_bytes(raw[i : i + 3], "big", signed=True) for i in (0, 3, 6)]
    gain = 0.3671 * 100 + 1.5
    m = np.array(counts) / gain
    mag = cage.physics.magnetometers["rm3100"]
    truth = mag.truth_reading(
        cage.physics.field_ut(noise=False), cage.physics.load_currents(time.monotonic())
    )
    assert np.all(np.abs(m - truth) < 0.15), (m, truth)
    assert _read(bus, 0x20, 0x34, 1)[0] & 0x80 == 0  # reading the results cleared DRDY


def test_rm3100_continuous_mode(cage: SimulatedCage) -> None:
    bus = cage.i2c_bus
    _write(bus, 0x20, 0x0B, [0x95])  # 75 Hz
    _write(bus, 0x20, 0x01, [0x79])  # CMM: start, DRDM = 10 (DRDY after each x y z set), x y z
    seen = 0
    period_s = 1 / 75
    t_end = time.monotonic() + 0.2
    # time covered by polls less than a period apart, and the longer gaps: a descheduled test
    # misses conversions there, as a real bus master would (each gap costs at most its length)
    polled_s, gaps = 0.0, 0
    last = time.monotonic()
    while (now := time.monotonic()) < t_end:
        if now - last < period_s:
            polled_s += now - last
        else:
            gaps += 1
        last = now
        if _read(bus, 0x20, 0x34, 1)[0] & 0x80:
            _read(bus, 0x20, 0x24, 9)
            seen += 1
        time.sleep(0.002)
    _read(bus, 0x20, 0x01, 1)  # reading CMM ends continuous mode
    assert seen <= 17  # never faster than 75 Hz (0.2 s)
    assert seen >= int(polled_s / period_s) - 2 - gaps, (seen, polled_s, gaps)


def test_i2c_nack_is_errno_121(cage: SimulatedCage) -> None:
    with pytest.raises(OSError) as info:
        _read(cage.i2c_bus, 0x21, 0x36, 1)  # nobody at 0x21
    assert info.value.errno == errno.EREMOTEIO == 121
    cage.faults["rm3100"].silent = True
    try:
        with pytest.raises(OSError):
            _read(cage.i2c_bus, 0x20, 0x36, 1)
    finally:
        cage.faults["rm3100"].silent = False
