"""The closed loop with an external flight computer over UDP (issue 56): the protocol's packets
(CCSDS space packets, docs/hil.md) both ways, the simulated B-dot flight computer of ``sim/``
(written apart from the rig's side) detumbling the same spacecraft as the in-process B-dot, and a
silent or garbled flight computer counted and said, the rods holding their last dipoles."""

from __future__ import annotations

import socket
import struct
import threading
from pathlib import Path

import numpy as np
import pytest

from rig.hil.external import ExternalFlightComputer, parse_address
from rig.hil.flight_software import default_gain
from rig.hil.packets import DIPOLE_APID, PacketError, decode, dipole_of, encode, readings_packet
from rig.steps.vocabulary import ProcedureError
from sim.flight_computer import BDotComputer
from tests.steps.fake_context import make_step
from tests.steps.test_closed_loop_step import LOOP, closed_loop_on_a_perfect_cage


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
    assert parse_address("udp://127.0.0.1:5005") == ("127.0.0.1", 5005)
    with pytest.raises(ProcedureError, match="give it as udp://HOST:PORT"):
        make_step("closed_loop", {**LOOP, "flight_computer": "tcp://127.0.0.1:5005"})


def test_the_simulated_flight_computer_detumbles_the_same_spacecraft(tmp_path: Path) -> None:
    computer = BDotComputer(default_gain(0.2), 0.2).start()
    try:
        # a generous wait for each answer: the flight computer's thread may wait for a CPU on a
        # busy computer, and this test is about what it answers, not how fast
        body = {**LOOP, "flight_computer": f"udp://127.0.0.1:{computer.port}",
                "reply_timeout_s": 5.0}  # fmt: skip
        external = closed_loop_on_a_perfect_cage(tmp_path / "external", body, lambda b: b)
    finally:
        computer.close()
    inside = closed_loop_on_a_perfect_cage(tmp_path / "inside", LOOP, lambda b: b)
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
