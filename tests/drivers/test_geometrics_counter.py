"""The Geometrics CM-201 counter driver (a cesium total-field magnetometer) against the maker's
manual: the ASCII output lines exactly as the G-882 manual prints them, the cycle command's
bytes, a lost Larmor signal, refusals and garbage; and the simulated counter read by pyserial
alone (not our transport) gives lines of the manual's format at the rate set."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest
import serial

from drivers.errors import DeviceProtocolError, DeviceRefusedError
from drivers.mag.geometrics_counter import GeometricsCounter, parse_line
from sim.cesium import CesiumCounter, counter_line
from sim.physics import Faults
from tests.drivers.scripted import Exchange, ScriptedSerialPeer

MANUAL_LINE = re.compile(rb"^\$[ 1]\d{5}\.\d{3},\d{4}\r\n$")
"""Chars 1-18 of the manual's ASCII format: '$', '1' or blank, 5 digits, '.', 3 digits, ',',
4 digits of signal level, CR, LF."""


def test_the_manuals_example_lines_parse() -> None:
    # the printout in the G-882 manual's output-format section
    assert parse_line(b"$ 49895.131,1249\r\n") == (49895.131, 1249)
    assert parse_line(b"$ 49995.071,1281\r\n") == (49995.071, 1281)
    assert parse_line(b"$100123.456,1200\r\n") == (100123.456, 1200)  # '1': above 99999.999 nT
    for bad in (b"$ 4989.131,1249\r\n", b"# 49895.131,1249\r\n", b"$ 49895.131\r\n",
                b"$ 49895.131,12a9\r\n", b"\x00\xff\r\n"):  # fmt: skip
        with pytest.raises(DeviceProtocolError, match="unreadable counter line"):
            parse_line(bad)


def test_cycle_command_signal_threshold_and_garbage() -> None:
    peer = ScriptedSerialPeer([
        Exchange(b"C00125\r", b"", delay_s=0.0),  # 8 Hz: 12.5 hundredths (the 5 ms digit)
        Exchange(b"C0010\r", b"$ 48231.250,1240\r\n", delay_s=0.0),
        Exchange(b"", b"$ 00000.000,0043\r\n"),  # no resonance: a dead zone
        Exchange(b"", b"\x00garbage\r\n$ 48231.300,1238\r\n"),
        Exchange(b"", b"ERR00:X9\r\n"),
    ])  # fmt: skip
    time.sleep(0.3)
    counter = GeometricsCounter(peer.path, baudrate=9600, min_signal=500)
    try:
        assert counter.set_cycle(8.0) == pytest.approx(8.0)
        assert counter.set_cycle(10.0) == pytest.approx(10.0)
        assert counter.read_total_nt() == 48231.25
        assert counter.read_total_nt() is None  # signal 43 < 500: not a measurement
        assert counter.read_total_nt() == 48231.3 and counter.bad_lines == 1
        with pytest.raises(DeviceRefusedError, match="refused a command"):
            counter.read_total_nt()
    finally:
        counter.close()
        peer.close()
    assert not peer.mismatches, peer.mismatches


def test_the_simulated_counter_speaks_the_manuals_format_to_pyserial() -> None:
    field = np.array([19.6, 1.2, -44.8])
    sim = CesiumCounter(lambda t: field, Faults(), optical_axis=np.array([0.0, 0.5, 1.0]),
                        offset_nt=1.0, heading_error_nt=0.0, dead_zone_deg=10.0, noise_nt=0.0,
                        baudrate=9600, seed=1)  # fmt: skip
    try:
        with serial.Serial(sim.path, 9600, timeout=2.0) as port:
            port.reset_input_buffer()
            port.readline()  # the partial line in flight
            lines = [port.readline() for _ in range(3)]
            port.write(b"C0050\r")  # 2 Hz
            deadline = time.monotonic() + 5.0
            while sim.cycle_s != 0.5 and time.monotonic() < deadline:
                time.sleep(0.01)
            port.write(b"Q\r")
            answer = b""
            while not answer.startswith(b"ERR"):
                answer = port.readline()
    finally:
        sim.close()
    assert all(MANUAL_LINE.match(line) for line in lines), lines
    expected = 1e3 * float(np.linalg.norm(field)) + 1.0
    assert parse_line(lines[0])[0] == pytest.approx(expected, abs=0.002)
    assert sim.cycle_s == 0.5 and answer == b"ERR00:Q\r\n"
    assert counter_line(48231.25, 1240) == b"$ 48231.250,1240\r\n"


def test_a_field_in_the_dead_zone_or_below_range_has_no_signal() -> None:
    for field in (
        np.array([0.0, 0.0, 48.0]),
        np.array([0.0, 0.05, 48.0]),
        np.array([3.0, 2.0, 5.0]),
    ):  # along the axis; near it; 6 uT: below 17 uT
        sim = CesiumCounter(lambda t, f=field: f, Faults(), optical_axis=np.array([0.0, 0.0, 1.0]),
                            offset_nt=0.0, heading_error_nt=0.0, dead_zone_deg=10.0,
                            noise_nt=0.0, baudrate=9600, seed=2)  # fmt: skip
        try:
            total, signal = sim.reading(time.monotonic())
        finally:
            sim.close()
        assert total == 0.0 and signal < 100
    tilted = np.array([30.0, 0.0, 30.0])  # 45 deg from the axis: locked
    sim = CesiumCounter(lambda t: tilted, Faults(), optical_axis=np.array([0.0, 0.0, 1.0]),
                        offset_nt=0.0, heading_error_nt=0.5, dead_zone_deg=10.0, noise_nt=0.0,
                        baudrate=9600, seed=3)  # fmt: skip
    try:
        total, signal = sim.reading(time.monotonic())
    finally:
        sim.close()
    assert signal > 1000 and total == pytest.approx(1e3 * 30 * 2**0.5 + 0.5 / 2**0.5, abs=1e-6)
