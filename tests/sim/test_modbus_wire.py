"""Simulated supplies, load and relays over Modbus TCP and RTU, read and written by Debian's mbpoll
(an independent libmodbus client) and by a plain pymodbus client for the faults."""

from __future__ import annotations

import re
import shutil
import subprocess
import time
from typing import Any

import pytest
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException

from sim.cage import SimulatedCage
from tests.tools import require_tool

pytestmark = pytest.mark.realtime

MBPOLL = shutil.which("mbpoll")


@pytest.fixture
def _mbpoll() -> str:
    return require_tool("mbpoll", what="the Modbus wire tests")


needs_mbpoll = pytest.mark.usefixtures("_mbpoll")


def mbpoll(
    dev: dict[str, Any], *args: str, write: list[str] | None = None
) -> subprocess.CompletedProcess[str]:
    assert MBPOLL is not None
    if dev["protocol"] == "modbus-tcp":
        where = ["-m", "tcp", "-p", str(dev["port"]), "-a", str(dev["device_id"])]
        target = "127.0.0.1"
    else:
        where = ["-m", "rtu", "-b", str(dev["baudrate"]), "-P", "none", "-a", str(dev["device_id"])]
        target = dev["path"]
    cmd = [MBPOLL, *where, "-0", "-1", "-o", "1", *args, target, *(write or [])]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=20)


def values(proc: subprocess.CompletedProcess[str]) -> dict[int, float]:
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return {int(a): float(v) for a, v in re.findall(r"^\[(\d+)\]:\s+(-?[\d.]+)", proc.stdout, re.M)}


@needs_mbpoll
@pytest.mark.parametrize("name", ["coil_x", "coil_y"])
def test_riden_over_tcp_and_rtu(devices: dict[str, Any], cage: SimulatedCage, name: str) -> None:
    dev = devices[name]
    regs = values(mbpoll(dev, "-r", "0", "-c", "4", "-t", "4"))
    assert regs[0] == 60065 and regs[2] == 12345  # RD6006P, serial low word
    for reg, value in (("8", "12000"), ("9", "15000"), ("18", "1")):  # 12.000 V, 1.5000 A, on
        assert mbpoll(dev, "-r", reg, "-t", "4", write=[value]).returncode == 0
    time.sleep(0.3)  # > 10 L/R time constants
    regs = values(mbpoll(dev, "-r", "8", "-c", "11", "-t", "4"))
    r_ohm = cage.physics.supplies[name].resistance_ohm
    # 12 V into ~4 ohm wants 3 A > 1.5 A: constant current at 1.50 A, V_OUT = I R
    assert regs[11] == 15000 and regs[17] == 1 and regs[18] == 1
    assert abs(regs[10] / 1000 - 1.5 * r_ohm) <= 0.001
    assert mbpoll(dev, "-r", "18", "-t", "4", write=["0"]).returncode == 0


@needs_mbpoll
def test_exception_replies(devices: dict[str, Any]) -> None:
    dev = devices["coil_x"]
    over = mbpoll(dev, "-r", "8", "-t", "4", write=["65000"])  # 65 V on a 60 V supply
    assert over.returncode != 0 and "Illegal data value" in over.stdout + over.stderr
    hole = mbpoll(dev, "-r", "500", "-t", "4")
    assert hole.returncode != 0 and "Illegal data address" in hole.stdout + hole.stderr
    ro = mbpoll(dev, "-r", "10", "-t", "4", write=["5"])  # V_OUT is read-only
    assert ro.returncode != 0 and "Illegal data address" in ro.stdout + ro.stderr


@needs_mbpoll
def test_electronic_load_float32_and_bias(devices: dict[str, Any], cage: SimulatedCage) -> None:
    """The simulated Maynuo as an independent client sees it: no function 06, its coils (remote
    PC1, input state ISTATE) read by function 01, and constant current only when selected: it
    powers up in CV (SETMODE 0xFF02), where a client that switches its input on without CMD 1
    sees it sink its full 30 A, not the 2.5 A asked."""
    dev = devices["load_panel"]
    assert mbpoll(dev, "-r", str(0x0A01), "-t", "4:float", "-B", write=["2.5"]).returncode == 0
    single = mbpoll(dev, "-r", str(0x0A00), "-t", "4", write=["42"])  # function 06
    assert single.returncode != 0 and "Illegal function" in single.stdout + single.stderr
    assert values(mbpoll(dev, "-r", str(0x0B04), "-t", "4"))[0x0B04] == 0xFF02  # CV
    assert values(mbpoll(dev, "-r", str(0x0500), "-c", "1", "-t", "0")) == {0x0500: 0}  # local
    client = ModbusTcpClient("127.0.0.1", port=dev["port"])
    assert client.connect()
    uid = dev["device_id"]
    assert not client.write_registers(0x0A00, [42], device_id=uid).isError()  # on, in CV
    time.sleep(0.1)
    assert abs(cage.physics.load_currents(time.monotonic())["load_panel"] - 30.0) < 1e-3
    assert not client.write_registers(0x0A00, [43], device_id=uid).isError()  # off
    assert not client.write_coil(0x0500, True, device_id=uid).isError()  # remote
    assert not client.write_registers(0x0A00, [1], device_id=uid).isError()  # CC
    assert values(mbpoll(dev, "-r", str(0x0B04), "-t", "4"))[0x0B04] == 0xFF01
    assert not client.write_registers(0x0A00, [42], device_id=uid).isError()  # on, in CC
    time.sleep(0.1)
    meas = values(mbpoll(dev, "-r", str(0x0B02), "-t", "4:float", "-B"))
    assert abs(meas[0x0B02] - 2.5) < 1e-3
    assert abs(cage.physics.load_currents(time.monotonic())["load_panel"] - 2.5) < 1e-3
    coils = values(mbpoll(dev, "-r", str(0x0500), "-c", "17", "-t", "0"))
    assert (coils[0x0500], coils[0x0510]) == (1, 1)  # remote, input on
    assert not client.write_registers(0x0A00, [43], device_id=uid).isError()  # off
    assert values(mbpoll(dev, "-r", str(0x0510), "-c", "1", "-t", "0")) == {0x0510: 0}
    assert not client.write_coil(0x0500, False, device_id=uid).isError()
    client.close()
    assert not cage.physics.supplies["load_panel"].output


@needs_mbpoll
def test_relay_polarity_and_hot_switch(devices: dict[str, Any], cage: SimulatedCage) -> None:
    relay, coil = devices["polarity"], devices["coil_z"]
    for reg, value in (("8", "8000"), ("9", "5000"), ("18", "1")):  # 8 V, 0.5 A on z
        assert mbpoll(coil, "-r", reg, "-t", "4", write=[value]).returncode == 0
    time.sleep(0.3)
    before = cage.physics.coil_currents()[2]
    assert abs(before - 0.5) < 1e-3
    hot = cage.physics.relays.hot_switches
    assert mbpoll(relay, "-r", "2", "-t", "4", write=["1"]).returncode == 0  # flip while live
    assert cage.physics.relays.hot_switches == hot + 1
    regs = values(mbpoll(coil, "-r", "16", "-c", "3", "-t", "4"))
    assert regs[16] == 2 and regs[18] == 0  # OCP latched, output off
    # the right way: current to zero, switch, then on again: the field reverses
    time.sleep(0.3)
    assert mbpoll(relay, "-r", "2", "-t", "4", write=["0"]).returncode == 0
    assert cage.physics.relays.hot_switches == hot + 1
    assert mbpoll(relay, "-r", "2", "-t", "4", write=["1"]).returncode == 0
    assert mbpoll(coil, "-r", "18", "-t", "4", write=["1"]).returncode == 0
    time.sleep(0.3)
    assert abs(cage.physics.coil_currents()[2] + 0.5) < 1e-3
    assert mbpoll(coil, "-r", "18", "-t", "4", write=["0"]).returncode == 0
    time.sleep(0.3)
    assert mbpoll(relay, "-r", "2", "-t", "4", write=["0"]).returncode == 0


CLIENT_TIMEOUT_S = 3.0
"""The independent client's timeout: long enough that a simulator descheduled by a loaded machine
(stress-ng beside the suite: no reply within 0.5 s was seen) still answers; the silent device
then costs this long."""


def test_injected_exception_timeout_and_disconnect(
    devices: dict[str, Any], cage: SimulatedCage
) -> None:
    dev = devices["coil_x"]
    faults = cage.faults["coil_x"]
    with ModbusTcpClient("127.0.0.1", port=dev["port"], timeout=CLIENT_TIMEOUT_S, retries=0) as c:
        assert c.read_holding_registers(0, count=1, device_id=1).registers == [60065]
        faults.exception_code = 6  # slave device busy
        try:
            rr = c.read_holding_registers(0, count=1, device_id=1)
        finally:
            faults.exception_code = 0
        assert rr.isError() and rr.exception_code == 6
        faults.silent = True
        try:
            with pytest.raises(ModbusException):
                c.read_holding_registers(0, count=1, device_id=1)
        finally:
            faults.silent = False
    with ModbusTcpClient("127.0.0.1", port=dev["port"], timeout=CLIENT_TIMEOUT_S, retries=0) as c:
        assert c.read_holding_registers(0, count=1, device_id=1).registers == [60065]
        cage.drop_connections("coil_x")
        time.sleep(0.1)
        with pytest.raises(ModbusException):
            c.read_holding_registers(0, count=1, device_id=1)


def test_rtu_corrupt_frames_and_silent_bus(devices: dict[str, Any], cage: SimulatedCage) -> None:
    dev = devices["load_bus"]
    faults = cage.faults["load_bus"]
    # 3 s: pymodbus cannot leave out a busy computer's pty stall (seconds beside CPU hogs) as our
    # driver does, and a healthy read timed out at 0.3 s with three test workers on two cores;
    # the silent bus below waits the whole of it
    with ModbusSerialClient(dev["path"], baudrate=dev["baudrate"], timeout=3.0, retries=0) as c:
        assert c.read_holding_registers(0, count=1, device_id=1).registers == [60062]
        faults.corrupt_rate = 1.0
        try:
            with pytest.raises(ModbusException):
                c.read_holding_registers(0, count=1, device_id=1)
        finally:
            faults.corrupt_rate = 0.0
        time.sleep(0.4)
        with pytest.raises(ModbusException):  # nobody at address 7 on this bus: silence
            c.read_holding_registers(0, count=1, device_id=7)
        time.sleep(0.4)
        c.close()
        c.connect()
        assert c.read_holding_registers(0, count=1, device_id=1).registers == [60062]


def test_a_read_of_126_registers_is_exception_3_on_the_wall_clocks_servers(
    devices: dict[str, Any],
) -> None:
    """The Modbus application protocol (6.3): a quantity beyond 125 registers is exception 3
    under function 3 (``83 03``), not an undecodable frame (``80 01``), on TCP and RTU."""
    import os
    import socket
    import struct
    import termios
    import tty

    request = struct.pack(">HHHBBHH", 0x0102, 0, 6, 1, 3, 0, 126)
    with socket.create_connection(("127.0.0.1", devices["coil_x"]["port"]), timeout=5.0) as s:
        s.sendall(request)
        reply = b""
        while len(reply) < 9 and (chunk := s.recv(64)):
            reply += chunk
    assert reply == struct.pack(">HHHBBB", 0x0102, 0, 3, 1, 0x83, 3)
    fd = os.open(devices["load_bus"]["path"], os.O_RDWR | os.O_NOCTTY)
    try:
        tty.setraw(fd)
        termios.tcflush(fd, termios.TCIOFLUSH)
        frame, refused = request[6:], bytes([1, 0x83, 3])
        assert _raw_request(fd, [frame + _crc(frame)]) == refused + _crc(refused)
    finally:
        os.close(fd)


def _crc(frame: bytes) -> bytes:
    from pymodbus.framer.rtu import FramerRTU

    return FramerRTU.compute_CRC(frame).to_bytes(2, "big")


def _raw_request(fd: int, pieces: list[bytes], wait_s: float = 0.5) -> bytes:
    """Write a request in ``pieces`` (a pause between them) and collect what comes back."""
    import os
    import select

    for i, piece in enumerate(pieces):
        if i:
            time.sleep(0.03)
        os.write(fd, piece)
    got = b""
    end = time.monotonic() + wait_s
    while (left := end - time.monotonic()) > 0 and len(got) < 7:
        if select.select([fd], [], [], left)[0]:
            got += os.read(fd, 256)
    return got


def test_rtu_request_in_pieces_is_answered_and_another_ids_stays_silent(
    devices: dict[str, Any],
) -> None:
    """The kernel may hand a request to the bus in pieces; the simulated RS-485 bus decides per
    frame whose it is (it dropped a piece that did not start with its id, then lost the next
    request with the half frame: over 1.5 s of silence on a busy machine)."""
    import os
    import termios
    import tty

    dev = devices["load_bus"]
    fd = os.open(dev["path"], os.O_RDWR | os.O_NOCTTY)
    try:
        tty.setraw(fd)
        termios.tcflush(fd, termios.TCIOFLUSH)
        ours = bytes([1, 3, 0, 0, 0, 1])
        ours += _crc(ours)
        theirs = bytes([7, 16, 0, 0, 0, 1, 2, 0, 5])
        theirs += _crc(theirs)
        expect = bytes([1, 3, 2]) + (60062).to_bytes(2, "big")
        expect += _crc(expect)
        assert _raw_request(fd, [ours]) == expect
        for cut in range(1, len(ours)):  # every split of our request
            assert _raw_request(fd, [ours[:cut], ours[cut:]]) == expect, cut
        # another station's write in pieces, then ours glued to its tail: silence, then our reply
        assert _raw_request(fd, [theirs[:3], theirs[3:]], wait_s=0.3) == b""
        assert _raw_request(fd, [theirs[:5], theirs[5:] + ours]) == expect
    finally:
        os.close(fd)
