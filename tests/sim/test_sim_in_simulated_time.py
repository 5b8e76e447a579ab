"""The whole simulated cage in simulated time (ADR 0038), driven with raw bytes over the clock's
wires: Modbus TCP on its loopback network, Modbus RTU and the serial magnetometers on
``simpipe://`` lines opened with pyserial. Times asserted are simulated seconds, exact: nothing
here depends on the computer's speed or load, and the same script gives the same bytes."""

from __future__ import annotations

import hashlib
import math
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
import serial
from pymodbus.framer.rtu import FramerRTU

import timebase
from sim.cage import SimulatedCage
from sim.config import load_config
from sim.hmr2300 import Hmr2300
from timebase.wires import PipeEnd, wires

pytestmark = pytest.mark.simcage

EPOCH_S = 1_767_225_600.0  # 2026-01-01 00:00 UTC: the simulated date at simulated time 0
R_V_SET, R_I_SET, R_I_OUT, R_OUTPUT = 8, 9, 11, 18  # Riden holding registers
RTU_BYTE_S = 10.0 / 115200  # one byte on the RTU lines of the default cage


@contextmanager
def simulated_cage() -> Iterator[tuple[SimulatedCage, dict[str, Any]]]:
    """The default cage started in simulated time (this thread on the clock); stopped inside."""
    with timebase.simulated(epoch_s=EPOCH_S):
        cage = SimulatedCage(load_config())
        devices = cage.start()["devices"]
        try:
            yield cage, devices
        finally:
            cage.stop()


def crc(frame: bytes) -> bytes:
    return FramerRTU.compute_CRC(frame).to_bytes(2, "big")


def rtu(unit: int, pdu: bytes) -> bytes:
    frame = bytes([unit]) + pdu
    return frame + crc(frame)


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def read_pdu(start: int, count: int) -> bytes:
    return struct.pack(">BHH", 3, start, count)


def write_pdu(address: int, value: int) -> bytes:
    return struct.pack(">BHH", 6, address, value)


def tcp_exchange(end: PipeEnd, request: bytes, timeout_s: float = 1.0) -> bytes:
    """One Modbus TCP request; the reply's bytes (header, then the length it gives)."""
    end.write(request)
    head = end.read(6, timeout_s)
    if len(head) < 6:
        return head
    return head + end.read(int.from_bytes(head[4:6], "big"), timeout_s)


def registers(reply: bytes) -> list[int]:
    """The registers of a Modbus TCP read reply."""
    count = reply[8] // 2
    return list(struct.unpack(f">{count}H", reply[9 : 9 + 2 * count]))


def test_endpoints_document_has_the_wall_clocks_shape() -> None:
    with SimulatedCage(load_config()) as wall:
        wall_devices = wall.endpoints_document()["devices"]
    with simulated_cage() as (_, devices):
        assert {n: sorted(d) for n, d in devices.items()} == {
            n: sorted(d) for n, d in wall_devices.items()
        }
        for name, entry in devices.items():
            assert entry["protocol"] == wall_devices[name]["protocol"]
            if entry["protocol"] == "modbus-tcp":
                assert entry["host"] == "127.0.0.1" and wires().listening(
                    "127.0.0.1", entry["port"]
                )
            elif "path" in entry:
                assert entry["path"] == f"simpipe://{name}"
        assert timebase.monotonic() == 0.0  # starting the cage takes no simulated time


def test_riden_registers_over_the_tcp_pipe_and_the_rtu_line() -> None:
    with simulated_cage() as (_, devices):
        end = wires().connect("127.0.0.1", devices["coil_x"]["port"])
        reply = tcp_exchange(end, mbap(0x1234, 1, read_pdu(0, 4)))
        assert reply[:9] == bytes.fromhex("12 34 00 00 00 0B 01 03 08")
        assert registers(reply) == [60065, 0, 12345, 140]  # RD6006P, serial number, firmware
        assert timebase.monotonic() == 0.0  # loopback TCP: no time on the wire

        port = serial.serial_for_url(devices["load_bus"]["path"], baudrate=115200, timeout=0.2)
        t0 = timebase.monotonic()
        port.write(rtu(1, read_pdu(0, 4)))
        answer = port.read(13)
        assert answer[:3] == bytes([1, 3, 8]) and answer[-2:] == crc(answer[:-2])
        assert struct.unpack(">4H", answer[3:11]) == (60062, 0, 12345, 140)  # RD6006
        # the request's 8 bytes and the reply's 13 bytes, each at 10 bits per byte at 115200 Bd
        assert timebase.monotonic() - t0 == pytest.approx((8 + 13) * RTU_BYTE_S, abs=1e-12)
        port.close()


@pytest.mark.parametrize("unit", [7, 0, 255])
def test_a_foreign_unit_id_gets_exception_11_on_tcp(unit: int) -> None:
    with simulated_cage() as (cage, devices):
        end = wires().connect("127.0.0.1", devices["coil_x"]["port"])
        reply = tcp_exchange(end, mbap(0x1234, unit, read_pdu(0, 1)))
        assert reply == bytes.fromhex("12 34 00 00 00 03") + bytes([unit, 0x83, 0x0B])
        write = tcp_exchange(end, mbap(0x1234, unit, write_pdu(R_OUTPUT, 1)))
        assert write == bytes.fromhex("12 34 00 00 00 03") + bytes([unit, 0x86, 0x0B])
        assert not cage.physics.supplies["coil_x"].output  # refused: nothing switched


# Modbus application protocol V1.1b3, 6.1-6.4: a quantity outside 1-2000 bits or 1-125 registers
# is answered with exception 3 (illegal data value) under the request's own function code
QUANTITY_BEYOND_LIMIT = [(1, 2001), (2, 2001), (3, 126), (4, 126), (3, 0)]


@pytest.mark.parametrize(("fc", "count"), QUANTITY_BEYOND_LIMIT)
def test_a_read_of_more_than_the_protocol_allows_is_exception_3(fc: int, count: int) -> None:
    with simulated_cage() as (_, devices):
        end = wires().connect("127.0.0.1", devices["coil_x"]["port"])
        pdu = struct.pack(">BHH", fc, 0, count)
        assert tcp_exchange(end, mbap(0x0102, 1, pdu)) == mbap(0x0102, 1, bytes([fc | 0x80, 3]))
        port = serial.serial_for_url(devices["load_bus"]["path"], baudrate=115200, timeout=0.2)
        port.write(rtu(1, pdu))
        assert port.read(5) == rtu(1, bytes([fc | 0x80, 3]))
        port.close()


def test_a_foreign_id_on_rtu_meets_silence() -> None:
    with simulated_cage() as (_, devices):
        port = serial.serial_for_url(devices["coil_y"]["path"], baudrate=115200, timeout=0.3)
        t0 = timebase.monotonic()
        port.write(rtu(7, read_pdu(0, 1)))
        assert port.read(7) == b""
        assert timebase.monotonic() - t0 == pytest.approx(0.3)  # the client's whole timeout
        port.write(rtu(1, read_pdu(0, 1)))
        assert port.read(7) == rtu(1, bytes([3, 2]) + (60065).to_bytes(2, "big"))
        port.close()


def test_a_set_point_and_the_coil_current_rising_with_its_time_constant() -> None:
    """Output on at t_on: the reported current is 1 A (1 - exp(-t / tau)), tau = L / R."""
    cfg = load_config()
    tau = cfg.cage.inductance_h[0] / cfg.cage.resistance_ohm[0]  # 25 ms
    with simulated_cage() as (cage, devices):
        end = wires().connect("127.0.0.1", devices["coil_x"]["port"])
        tcp_exchange(end, mbap(1, 1, write_pdu(R_V_SET, 12000)))  # 12 V, 1 mV counts
        tcp_exchange(end, mbap(2, 1, write_pdu(R_I_SET, 10000)))  # 1 A, 0.1 mA counts: CC
        timebase.sleep(0.5)
        t_on = timebase.monotonic()
        assert tcp_exchange(end, mbap(3, 1, write_pdu(R_OUTPUT, 1)))[7:] == write_pdu(R_OUTPUT, 1)
        seen = []
        for k in range(5):
            timebase.sleep(t_on + k * tau - timebase.monotonic())
            seen.append(registers(tcp_exchange(end, mbap(10 + k, 1, read_pdu(R_I_OUT, 1))))[0])
        assert seen == [round(1e4 * (1 - math.exp(-k))) for k in range(5)]
        assert cage.physics.coil_currents()[0] == pytest.approx(1 - math.exp(-4), abs=1e-12)
        timebase.sleep(10 * tau)
        assert cage.physics.coil_currents()[0] == pytest.approx(1.0, abs=1e-4)


def hmr_command(port: serial.Serial, *commands: str) -> bytes:
    """Write-enabled HMR2300 commands (``*99WE`` before each); the replies."""
    for command in commands:
        port.write(b"*99WE\r*99" + command.encode("ascii") + b"\r")
    timebase.sleep(0.1)
    return bytes(port.read(port.in_waiting))


def stream_hmr2300(port: serial.Serial, seconds: float,
                   during: Callable[[float], None] | None = None) -> list[tuple[float, bytes]]:  # fmt: skip
    """Stream binary frames for ``seconds``: (simulated arrival time, frame) each;
    ``during(t)`` is called after each frame."""
    port.write(b"*99C\r")
    frames: list[tuple[float, bytes]] = []
    t_end = timebase.monotonic() + seconds
    while timebase.monotonic() < t_end:
        frame = port.read(7)
        assert len(frame) == 7 and frame[6] == 0x0D
        frames.append((timebase.monotonic(), frame))
        if during is not None:
            during(frames[-1][0])
    port.write(b"\x1b")
    timebase.sleep(0.05)
    port.reset_input_buffer()
    return frames


def test_hmr2300_streams_154_binary_sps_at_19200_dated_by_simulated_time() -> None:
    cfg = load_config()
    tau = cfg.cage.inductance_h[0] / cfg.cage.resistance_ohm[0]
    with simulated_cage() as (cage, devices):
        device = cage.serial_devices["dut"]
        assert isinstance(device, Hmr2300)
        port = serial.serial_for_url(devices["dut"]["path"], baudrate=19200, timeout=0.5)
        assert hmr_command(port, "B", "R=154") == b"OK\rBINARY ON\rOK\rOK\r"
        coil = wires().connect("127.0.0.1", devices["coil_x"]["port"])
        tcp_exchange(coil, mbap(1, 1, write_pdu(R_V_SET, 12000)))
        tcp_exchange(coil, mbap(2, 1, write_pdu(R_I_SET, 10000)))
        switched: list[float] = []

        def switch_on_at_half_time(t: float) -> None:
            if not switched and t >= t_stream + 0.5:
                switched.append(timebase.monotonic())
                tcp_exchange(coil, mbap(3, 1, write_pdu(R_OUTPUT, 1)))

        t_stream = timebase.monotonic()
        frames = stream_hmr2300(port, 1.0, switch_on_at_half_time)
        port.close()
    times = np.array([t for t, _ in frames])
    line_s = 7 * 10 / 19200  # a frame's time on the line
    start = device.stream_start_s
    assert start == pytest.approx(t_stream + 5 * 10 / 19200)  # when "*99C\r" had arrived
    # frame k left at slot k of the device's 154 sps clock and arrived a frame's time later
    assert np.allclose(times - start - line_s, np.arange(len(times)) / 154, atol=1e-9)
    assert np.count_nonzero(times - start < 1.0) == 154  # 154 sps
    counts = np.array([struct.unpack(">hhh", f[:6]) for _, f in frames], float)
    due = times - line_s
    before = counts[due < switched[0]].mean(axis=0)
    change = counts[-1] - before  # 0.5 s = 20 tau after the switch: settled
    fraction = (counts - before) @ change / (change @ change)
    after = due >= switched[0]
    expected = 1 - np.exp(-(due[after] - switched[0]) / tau)
    assert np.allclose(fraction[after], expected, atol=0.01)  # each frame at its own slot's time
    assert np.abs(fraction[~after]).max() < 0.01


def test_the_ascii_reference_streams_at_20_hz() -> None:
    with simulated_cage() as (_, devices):
        port = serial.serial_for_url(devices["reference"]["path"], baudrate=115200, timeout=0.5)
        timebase.sleep(1.0)
        port.reset_input_buffer()  # what came before, and a line cut by opening the port
        port.readline()
        lines: list[tuple[float, list[float]]] = []
        while len(lines) < 100:
            line = port.readline()
            lines.append((timebase.monotonic(), [float(v) for v in line.split()]))
        port.close()
    times = np.array([t for t, _ in lines])
    values = np.array([v for _, v in lines])
    # a line every 50 ms, give or take the line time of a few characters more or less
    assert np.allclose(np.diff(times), 0.05, atol=5 * 10 / 115200)
    assert (times[-1] - times[0]) / (len(times) - 1) == pytest.approx(0.05, abs=1e-4)
    field = np.linalg.norm(values, axis=1)  # the lab field, about 49 uT
    assert np.all(np.abs(field - 49.0) < 2.0) and values.std(axis=0).max() < 0.05


def test_injected_reply_delay_exception_silence_and_dropped_connections() -> None:
    with simulated_cage() as (cage, devices):
        faults = cage.faults["coil_x"]
        end = wires().connect("127.0.0.1", devices["coil_x"]["port"])
        request = mbap(1, 1, read_pdu(0, 1))
        answer = tcp_exchange(end, request)
        assert registers(answer) == [60065]

        faults.reply_delay_s = 0.25
        t0 = timebase.monotonic()
        assert tcp_exchange(end, request) == answer
        # as on the wall clock: the device's own delay, then the link's
        assert timebase.monotonic() - t0 == pytest.approx(2 * 0.25)
        faults.reply_delay_s = 0.0

        faults.exception_code = 6  # server device busy
        assert tcp_exchange(end, request)[7:] == bytes([0x83, 6])
        faults.exception_code = 0

        faults.silent = True
        t0 = timebase.monotonic()
        assert tcp_exchange(end, request, timeout_s=2.0) == b""
        assert timebase.monotonic() - t0 == pytest.approx(2.0)
        faults.silent = False
        assert tcp_exchange(end, request) == answer  # the same connection answers again

        cage.drop_connections("coil_x")
        assert end.peer_closed and end.read(6, 1.0) == b""
        assert timebase.monotonic() - t0 == pytest.approx(2.0)  # closed at once: no timeout
        again = wires().connect("127.0.0.1", devices["coil_x"]["port"])
        assert tcp_exchange(again, request) == answer

        faults.disconnect = True
        assert tcp_exchange(again, request) == b"" and again.peer_closed  # at its next request
        assert wires().connect("127.0.0.1", devices["coil_x"]["port"]).peer_closed  # at once
        faults.disconnect = False


def test_rtu_reply_delay_corruption_and_silence() -> None:
    with simulated_cage() as (cage, devices):
        faults = cage.faults["load_bus"]
        port = serial.serial_for_url(devices["load_bus"]["path"], baudrate=115200, timeout=0.5)
        request = rtu(1, read_pdu(0, 1))
        port.write(request)
        answer = port.read(7)
        assert answer == rtu(1, bytes([3, 2]) + (60062).to_bytes(2, "big"))

        faults.reply_delay_s = 0.1
        t0 = timebase.monotonic()
        port.write(request)
        assert port.read(7) == answer
        assert timebase.monotonic() - t0 == pytest.approx(2 * 0.1 + (8 + 7) * RTU_BYTE_S)
        faults.reply_delay_s = 0.0

        faults.corrupt_rate = 1.0  # one bit flipped in every reply: its CRC fails
        port.write(request)
        damaged = port.read(7)
        assert len(damaged) == 7 and damaged != answer
        assert bin(int.from_bytes(damaged, "big") ^ int.from_bytes(answer, "big")).count("1") == 1
        faults.corrupt_rate = 0.0

        faults.silent = True
        port.write(request)
        assert port.read(7) == b""
        faults.silent = False
        port.write(request)
        assert port.read(7) == answer
        port.close()


def transcript() -> str:
    """A short session on the cage, every byte received and its simulated time hashed: two
    participants (this thread and a reader of the reference) over Modbus TCP and RTU, the
    HMR2300's stream, the reference's lines and the cesium counter's."""
    h = hashlib.sha256()
    with simulated_cage() as (cage, devices):

        def log(label: str, data: bytes) -> None:
            h.update(f"{timebase.monotonic():.9f} {label} ".encode() + data + b"\n")

        reference = serial.serial_for_url(devices["reference"]["path"], baudrate=115200,
                                          timeout=0.5)  # fmt: skip

        def read_reference() -> None:
            for _ in range(30):
                log("reference", reference.readline())

        reader = timebase.Thread(read_reference, name="reference-reader")
        reader.start()
        coil = wires().connect("127.0.0.1", devices["coil_z"]["port"])
        for k, (reg, value) in enumerate(((R_V_SET, 20000), (R_I_SET, 5000), (R_OUTPUT, 1))):
            log("coil_z", tcp_exchange(coil, mbap(k, 1, write_pdu(reg, value))))
        hmr = serial.serial_for_url(devices["dut"]["path"], baudrate=19200, timeout=0.5)
        log("dut", hmr_command(hmr, "B", "R=154"))
        for t, frame in stream_hmr2300(hmr, 0.5):
            h.update(f"{t:.9f} ".encode() + frame)
        bus = serial.serial_for_url(devices["load_bus"]["path"], baudrate=115200, timeout=0.2)
        for _ in range(3):
            bus.write(rtu(1, read_pdu(8, 6)))
            log("load_bus", bus.read(17))
            log("coil_z", tcp_exchange(coil, mbap(9, 1, read_pdu(R_I_OUT, 1))))
        cesium = serial.serial_for_url(devices["cesium"]["path"], baudrate=9600, timeout=0.5)
        cesium.reset_input_buffer()  # the lines since the start: read live ones
        for _ in range(3):
            log("cesium", cesium.readline())
        reader.join()
        log("field", np.array2string(cage.physics.field_ut(), precision=12).encode())
    return h.hexdigest()


@contextmanager
def cpu_hogs() -> Iterator[None]:
    """Two threads of this interpreter and two processes spinning while the block runs."""
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            sum(i * i for i in range(10_000))

    threads = [threading.Thread(target=spin, daemon=True) for _ in range(2)]
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    for t in threads:
        t.start()
    try:
        yield
    finally:
        stop.set()
        for p in procs:
            p.kill()
            p.wait()
        for t in threads:
            t.join()


def test_the_same_script_gives_byte_identical_transcripts_under_any_load() -> None:
    first = transcript()
    assert transcript() == first
    with cpu_hogs():
        assert transcript() == first


def test_sixty_simulated_seconds_of_hmr2300_streaming(capsys: pytest.CaptureFixture[str]) -> None:
    """Every frame of a minute's stream arrives; how long the minute took is printed (no
    assertion on it: that is the computer's)."""
    started = time.perf_counter()
    with simulated_cage() as (cage, devices):
        device = cage.serial_devices["dut"]
        assert isinstance(device, Hmr2300)
        port = serial.serial_for_url(devices["dut"]["path"], baudrate=19200, timeout=0.5)
        hmr_command(port, "B", "R=154")
        frames = stream_hmr2300(port, 60.0)
        clock = timebase.current()
        switches = getattr(clock, "switches", 0)
    wall_s = time.perf_counter() - started
    assert abs(len(frames) - 60 * 154) <= 1 and device.samples_skipped == 0
    assert device.bytes_overrun == 0
    with capsys.disabled():
        print(f"\n60 s of simulated HMR2300 streaming ({len(frames)} frames at 154 sps, the whole"
              f" cage running, {switches} turns): {wall_s:.2f} s of wall time")  # fmt: skip
