"""Security: the simulated cage listens on the loopback interface only."""

from __future__ import annotations

from pathlib import Path

import pytest

from sim.cage import SimulatedCage
from sim.config import load_config

pytestmark = pytest.mark.realtime


def listening_addresses() -> dict[int, str]:
    """Port -> local address (hex, as the kernel lists it) of every listening TCP socket."""
    out: dict[int, str] = {}
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        path = Path(table)
        if not path.exists():
            continue
        for line in path.read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            if state == "0A":  # LISTEN
                addr, port = local.split(":")
                out[int(port, 16)] = addr
    return out


def test_every_simulated_tcp_device_listens_on_127_0_0_1() -> None:
    with SimulatedCage(load_config()) as cage:
        devices = cage.endpoints_document()["devices"]
        tcp = {name: d for name, d in devices.items() if d.get("protocol") == "modbus-tcp"}
        assert tcp, "the default cage has Modbus TCP devices"
        listening = listening_addresses()
        for name, dev in tcp.items():
            assert dev["host"] == "127.0.0.1", name
            assert listening.get(dev["port"]) == "0100007F", (name, listening.get(dev["port"]))
