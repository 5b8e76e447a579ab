"""The closed loop with an external flight computer over UDP or a serial line (issue 56): the
protocol's packets (CCSDS space packets, docs/hil.md) both ways, on a serial line each after the
sync marker and found again after garbage, the simulated B-dot flight computer of ``sim/``
(written apart from the rig's side) detumbling the same spacecraft as the in-process B-dot over
either, and a silent or garbled flight computer counted and said, the rods holding their last
dipoles."""

from __future__ import annotations

import socket
import struct
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rig.errors import UserInputError
from rig.hil.external import ExternalFlightComputer
from rig.hil.flight_links import SYNC_MARKER, Address, SerialLink, parse_address
from rig.hil.flight_software import default_gain
from rig.hil.packets import DIPOLE_APID, PacketError, decode, dipole_of, encode, readings_packet
from rig.steps.vocabulary import ProcedureError
from sim.flight_computer import BDotComputer, SerialFrontEnd
from tests.steps.fake_context import make_step
from tests.steps.test_closed_loop_step import LOOP, closed_loop_on_a_perfect_cage

pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def inside(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The same scenario with the in-process B-dot: what each external flight computer is held
    to (run once for the module)."""
    return closed_loop_on_a_perfect_cage(tmp_path_factory.mktemp("inside"), LOOP, lambda b: b)


def test_packets_round_trip_and_refuse_what_is_not_one() -> None:
    raw = readings_packet(16385, 12.5, (30.0, -1.5, 2.25))
    header = struct.unpack(">HHH", raw[:6])
    assert header == (0x0A1, 0b11 << 14 | 1, 31)  # telemetry, APID, unsegmented, count mod 2^14
    packet = decode(raw)
    assert (packet.kind, packet.sequence) == (0, 1)
    assert struct.unpack(">4d", packet.data) == (12.5, 30.0, -1.5, 2.25)
    answer = decode(encode(1, DIPOLE_APID, 1, struct.pack(">3d", 0.1, -0.2, 0.0)))
    assert dipole_of(answer) == (0.1, -0.2, 0.0)
    for bad, says in [(raw[:5], "shorter than a packet"), (raw + b"x", "where the header says"),
                      (b"\xe0" + raw[1:], "version 7"), (b"\x08" + raw[1:], "secondary header")]:  # fmt: skip
        with pytest.raises(PacketError, match=says):
            decode(bad)
    with pytest.raises(PacketError, match="not a dipole packet"):
        dipole_of(packet)


def test_an_address_that_is_not_udp_is_refused_when_the_procedure_is_read() -> None:
    assert parse_address("udp://127.0.0.1:5005") == Address("udp", "127.0.0.1", 5005)
    assert parse_address("serial:///dev/ttyUSB0") == Address("serial", "/dev/ttyUSB0", 115200)
    assert parse_address("serial:///dev/ttyS1?baud=9600") == Address("serial", "/dev/ttyS1", 9600)
    for bad in ("tcp://127.0.0.1:5005", "serial://dev/ttyUSB0", "serial:///dev/ttyS1?baud=fast",
                "serial:///dev/ttyS1?speed=9600", "udp://127.0.0.1"):  # fmt: skip
        with pytest.raises(
            ProcedureError, match="give it as udp://HOST:PORT or serial:///dev/PORT"
        ):
            make_step("closed_loop", {**LOOP, "flight_computer": bad})
    with pytest.raises(
        UserInputError, match=r"cannot open it .* check the cable and the port name"
    ):
        ExternalFlightComputer("serial:///dev/no-such-port", 0.1)


def test_the_simulated_flight_computer_detumbles_the_same_spacecraft(
    tmp_path: Path, inside: dict[str, Any]
) -> None:
    computer = BDotComputer(default_gain(0.2), 0.2).start()
    try:
        # a generous wait for each answer: the flight computer's thread may wait for a CPU on a
        # busy computer, and this test is about what it answers, not how fast
        body = {**LOOP, "flight_computer": f"udp://127.0.0.1:{computer.port}",
                "reply_timeout_s": 5.0}  # fmt: skip
        external = closed_loop_on_a_perfect_cage(tmp_path / "external", body, lambda b: b)
    finally:
        computer.close()
    link = external["flight_computer"]
    assert link["missed"] == 0 and link["answered"] > 100, link
    assert external["flight_software"].startswith("external flight computer at udp://")
    assert external["detumble_s"] == pytest.approx(inside["detumble_s"], rel=0.05)
    assert abs(external["difference_pct"]) < 10.0, external["summary"]
    print(f"external flight computer: {external['summary']}; in process: {inside['summary']};"
          f" round trip p99 {link['round_trip_ms_p99']:.2f} ms")  # fmt: skip


def test_a_silent_or_garbled_flight_computer_is_counted_and_the_rods_hold() -> None:
    server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    server.bind(("127.0.0.1", 0))
    port = server.getsockname()[1]
    replies: list[bytes] = [encode(1, DIPOLE_APID, 0, struct.pack(">3d", 0.1, 0.0, -0.1)),
                            b"\x00\x01garbage", b""]  # fmt: skip

    def answer() -> None:
        for reply in replies:
            _raw, peer = server.recvfrom(2048)
            if reply:
                server.sendto(reply, peer)

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    # 2 s: the answering thread may wait for a CPU on a busy computer (the silent call waits it out)
    fc = ExternalFlightComputer(f"udp://127.0.0.1:{port}", reply_timeout_s=2.0)
    try:
        first = fc.dipole(np.array([30.0, 0.0, 0.0]), 0.5)
        garbled = fc.dipole(np.array([30.0, 0.1, 0.0]), 1.0)
        silent = fc.dipole(np.array([30.0, 0.2, 0.0]), 1.5)
    finally:
        fc.close()
        server.close()
    assert first == pytest.approx([0.1, 0.0, -0.1])
    assert garbled == pytest.approx(first) and silent == pytest.approx(first)  # the rods hold
    assert (fc.answered, fc.missed) == (1, 2)
    assert fc.problem is not None and fc.problem.startswith("a packet that is not a dipole packet")


def test_the_simulated_flight_computer_on_a_serial_line_detumbles_the_same_spacecraft(
    tmp_path: Path, inside: dict[str, Any]
) -> None:
    """The flight computer on a pseudo-terminal (as on a USB serial adapter): the rig's end opens
    it as a serial port, each packet after the sync marker."""
    front = SerialFrontEnd(BDotComputer(default_gain(0.2), 0.2)).start()
    try:
        body = {**LOOP, "flight_computer": f"serial://{front.port}", "reply_timeout_s": 5.0}
        serial = closed_loop_on_a_perfect_cage(tmp_path / "serial", body, lambda b: b)
    finally:
        front.close()
    link = serial["flight_computer"]
    assert link["missed"] == 0 and link["answered"] > 100, link
    assert serial["flight_software"] == f"external flight computer at serial://{front.port}"
    assert serial["detumble_s"] == pytest.approx(inside["detumble_s"], rel=0.05)
    print(f"serial flight computer: {serial['summary']}; round trip p99"
          f" {link['round_trip_ms_p99']:.2f} ms")  # fmt: skip


def test_a_serial_line_finds_each_packet_after_garbage_and_split_reads() -> None:
    """Bytes lost or garbled on the line cost only the packets they touch: the receiver hunts
    for the marker, passes over a false marker whose length no packet has, and joins a packet
    that arrives in pieces."""
    import os
    import tty

    leader, follower = os.openpty()
    tty.setraw(follower)
    link = SerialLink(Address("serial", os.ttyname(follower), 115200))
    try:
        good = encode(1, DIPOLE_APID, 7, struct.pack(">3d", 0.1, -0.2, 0.05))
        false_marker = SYNC_MARKER + b"\x10\xa2\xc0\x07\xff\xff"  # 65536 bytes: no packet of ours
        os.write(leader, b"\x00noise" + false_marker + SYNC_MARKER + good[:10])
        import time

        assert link.receive(time.monotonic() + 0.2) is None  # not all there yet
        os.write(leader, good[10:] + b"\x1a\xcf" + SYNC_MARKER + good)
        first = link.receive(time.monotonic() + 2.0)
        second = link.receive(time.monotonic() + 2.0)
        assert first == good and second == good
        assert dipole_of(decode(first)) == (0.1, -0.2, 0.05)
        assert link.skipped == len(b"\x00noise") + len(false_marker) + 2
        link.send(good)
        assert os.read(leader, 100) == SYNC_MARKER + good
    finally:
        link.close()
        os.close(leader)
        os.close(follower)


@pytest.mark.parametrize("how", [["--port", "0"], ["--pty"]])
def test_the_documented_flight_computer_commands_answer_a_readings_packet(how: list[str]) -> None:
    """docs/hil.md's ``python -m sim.flight_computer --port 5005`` (here any free port) and
    ``--pty``: each prints where it answers, and answers two readings with B-dot's dipoles."""
    import signal
    import subprocess
    import sys

    from rig.child_process import stop_child

    proc = subprocess.Popen([sys.executable, "-m", "sim.flight_computer", *how],
                            stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert proc.stdout is not None
        said = proc.stdout.readline().strip()
        assert said.startswith("flight computer: B-dot on "), said
        fc = ExternalFlightComputer(said.rsplit(" ", 1)[1], reply_timeout_s=10.0)
        try:
            fc.dipole(np.array([30.0, 0.0, 0.0]), 0.5)
            second = fc.dipole(np.array([30.0, 1.0, 0.0]), 1.0)  # 2 uT/s along y
        finally:
            fc.close()
        assert (fc.answered, fc.missed) == (2, 0)
        assert second == pytest.approx([0.0, -0.2, 0.0])  # clipped at the 0.2 A m^2 default
    finally:
        stop_child(proc, first=signal.SIGTERM, wait_s=10.0)  # its pipe closed too
