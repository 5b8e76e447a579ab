"""Every Write Single Register (function 6) reply of the simulated register-map devices is an
echo of its request, byte for byte (Modbus application protocol 6.6), for each writable 16-bit
register of their maps, including writes that trip a protection. The Riden's are in
test_riden_sim.py."""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Iterator

import pytest

from regmaps import load_map
from sim.cage import SimulatedCage
from tests.conformance.simcage import cage_with, endpoint

pytestmark = pytest.mark.realtime

SWAPS = {
    "coil_x": 'kind = "regmap"\nregmap = "hm310p"',
    "coil_z": 'kind = "regmap"\nregmap = "dps5005"',
}


@pytest.fixture(scope="module")
def cage(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimulatedCage]:
    with cage_with(tmp_path_factory.mktemp("echo"), SWAPS) as c:
        yield c


def exchange(port: int, pdu: bytes, tid: int) -> tuple[bytes, bytes]:
    request = struct.pack(">HHHB", tid, 0, len(pdu) + 1, 1) + pdu
    with socket.create_connection(("127.0.0.1", port), timeout=2.0) as sock:
        sock.sendall(request)
        head = b""
        while len(head) < 6:
            head += sock.recv(6 - len(head))
        length = struct.unpack(">H", head[4:6])[0]
        body = b""
        while len(body) < length:
            body += sock.recv(length - len(body))
    return request, head + body


def writes_for(regmap: str) -> list[tuple[int, int]]:
    """(address, value) for every writable 16-bit register: a small value that fits, then a
    protection trip where the map has the levels."""
    spec = load_map(regmap)
    out = [(r.address, 1) for r in spec.registers if r.access == "rw" and r.width == 1
           and r.role not in ("output", "ovp", "ocp")]  # fmt: skip
    v_set, i_set, output = spec.require("v_set"), spec.require("i_set"), spec.require("output")
    out += [(v_set.address, v_set.encode(5.0)[0]), (i_set.address, i_set.encode(1.0)[0]),
            (output.address, 1)]  # fmt: skip
    ocp = spec.role("ocp")
    if ocp is not None:  # OCP below the output: trips while answering
        out += [(ocp.address, ocp.encode(0.1)[0]), (output.address, 1)]
    out += [(output.address, 0)]
    return out


@pytest.mark.parametrize(("name", "regmap"), [("coil_x", "hm310p"), ("coil_z", "dps5005"),
                                              ("polarity", "relay-h-bridge")])  # fmt: skip
def test_every_write_single_register_reply_is_an_echo(
    cage: SimulatedCage, name: str, regmap: str
) -> None:
    port = int(endpoint(cage, name)["port"])
    for tid, (address, value) in enumerate(writes_for(regmap) if regmap != "relay-h-bridge" else
                                           [(0, 0), (1, 0), (2, 0)], 1):  # fmt: skip
        request, reply = exchange(port, struct.pack(">BHH", 6, address, value), tid)
        assert reply == request, f"{regmap} register {address:#06x} = {value}: {reply.hex(' ')}"
        time.sleep(0.01)
    if regmap == "hm310p":  # the OCP trip happened (latched) though each reply was an echo
        assert cage.physics.supplies[name].protection == 2
