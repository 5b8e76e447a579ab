"""The simulated HMR2300 against its datasheet's command table (Honeywell HMR2300, "Command
Inputs"), in simulated time over a ``simpipe://`` line read with pyserial: the replies' byte
counts (``*dd#`` 22 bytes, ``*ddF`` 27) and the one-line form ``*ddWE *ddCMD`` that the table
writes for every write-protected command and public drivers send (itu-rover's reads exactly 22
bytes after ``*99#`` and exactly the command's reply after ``*99WE *99B``)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import serial

import timebase
from drivers.mag.hmr2300 import Hmr2300 as Hmr2300Driver
from sim.hmr2300 import Hmr2300
from sim.physics import Faults

pytestmark = pytest.mark.realtime


@pytest.fixture()
def sensor() -> Iterator[Hmr2300]:
    with timebase.simulated():
        device = Hmr2300(lambda _t: np.array([20.0, -5.0, 45.0]), Faults(), baudrate=9600)
        try:
            yield device
        finally:
            device.close()


def ask(port: serial.Serial, line: bytes, n: int) -> bytes:
    """``line`` sent, then exactly ``n`` bytes read (fewer after the port's timeout)."""
    port.write(line)
    return bytes(port.read(n))


def test_serial_number_and_software_version_have_the_datasheets_lengths(sensor: Hmr2300) -> None:
    port = serial.serial_for_url(sensor.path, baudrate=9600, timeout=0.5)
    serial_reply = ask(port, b"*00#\r", 22)
    assert len(serial_reply) == 22 and serial_reply.startswith(b"SER# 0123")
    assert serial_reply.endswith(b"\r") and b"\r" not in serial_reply[:-1]
    version = ask(port, b"*00F\r", 27)
    assert len(version) == 27 and version.startswith(b"S/W vers: 3.12")
    assert version.endswith(b"\r") and b"\r" not in version[:-1]
    assert port.read(1) == b""  # nothing more
    port.close()
    driver = Hmr2300Driver(sensor.path, baudrate=9600, device_id=0, set_reset_auto=False)
    ident = driver.identify()
    assert (ident.model, ident.serial, ident.firmware) == ("HMR2300", "0123", "3.12")
    driver.close()


def test_write_enable_and_its_command_on_one_line(sensor: Hmr2300) -> None:
    port = serial.serial_for_url(sensor.path, baudrate=9600, timeout=0.5)
    assert ask(port, b"*00WE *00B\r", 10) == b"BINARY ON\r"  # the command's reply only
    assert sensor.binary
    assert ask(port, b"*99WE *99R=50\r", 3) == b"OK\r" and sensor.rate_sps == 50
    assert ask(port, b"*00A\r", 7) == b"WE OFF\r"  # the line's WE covered its command only
    assert ask(port, b"*00WE *00A\r", 9) == b"ASCII ON\r" and not sensor.binary
    assert ask(port, b"*01WE *01B\r", 10) == b""  # another sensor's: this one stays silent
    assert port.read(1) == b""
    port.close()
