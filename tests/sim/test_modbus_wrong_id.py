"""A wrong Modbus device id against the simulated cage over real TCP and a real pty: what the wire
carries (TCP: exception 11 from the endpoint, as from a gateway; RTU: silence, as on RS-485) and
what the driver says (the id, and where to look), unlike a real device failure (exception 4)."""

from __future__ import annotations

import socket
import struct
import time
from typing import Any

import pytest

from drivers.errors import DeviceAbsentError, DeviceRefusedError, DeviceTimeoutError
from drivers.registry import KINDS, OpenSpec
from drivers.transport.modbus import ModbusLink
from sim.cage import SimulatedCage

pytestmark = pytest.mark.realtime


def tcp_exchange(port: int, unit: int, pdu: str) -> bytes:
    """One Modbus TCP request (transaction id 0x1234) on a fresh connection; the raw reply."""
    body = bytes.fromhex(pdu)
    with socket.create_connection(("127.0.0.1", port), timeout=2.0) as s:
        s.sendall(struct.pack(">HHHB", 0x1234, 0, len(body) + 1, unit) + body)
        return s.recv(256)


@pytest.mark.parametrize("unit", [7, 0, 255])
def test_tcp_endpoint_answers_exception_11_for_a_unit_id_it_does_not_serve(
    devices: dict[str, Any], unit: int
) -> None:
    port = devices["coil_x"]["port"]
    served = tcp_exchange(port, 1, "03 00 00 00 01")
    assert served == bytes.fromhex("12 34 00 00 00 05 01 03 02 EA A1")  # RD6006P, id 1
    reply = tcp_exchange(port, unit, "03 00 00 00 01")
    assert reply == bytes.fromhex("12 34 00 00 00 03") + bytes([unit, 0x83, 0x0B])
    write = tcp_exchange(port, unit, "06 00 12 00 01")  # output on: refused, nothing switched
    assert write == bytes.fromhex("12 34 00 00 00 03") + bytes([unit, 0x86, 0x0B])


def test_riden_opened_with_a_wrong_tcp_id_names_the_id(devices: dict[str, Any]) -> None:
    dev = devices["coil_x"]
    spec = OpenSpec("coil_x", "modbus-tcp", {"host": "127.0.0.1", "port": dev["port"],
                                             "device_id": 7})  # fmt: skip
    started = time.monotonic()
    with pytest.raises(DeviceAbsentError) as info:
        KINDS["riden-rd60xx"].open(spec)
    assert time.monotonic() - started < 1.0  # an answer, not a timeout: no retries
    message = str(info.value)
    assert message.startswith(
        f"coil_x at 127.0.0.1:{dev['port']}: no device with unit id 7 answers (the gateway"
        " replied Modbus exception 11, gateway target device failed to respond, to reading"
    )
    assert "device_id = 7" in message and "menu or DIP switches" in message
    assert "device failure" not in message


def test_riden_opened_with_a_wrong_rtu_id_names_the_id(
    devices: dict[str, Any], cage: SimulatedCage
) -> None:
    dev = devices["load_bus"]
    params = {"path": dev["path"], "baudrate": dev["baudrate"], "device_id": 7, "timeout_s": 0.3}
    with pytest.raises(DeviceTimeoutError) as info:
        KINDS["riden-rd60xx"].open(OpenSpec("load_bus", "modbus-rtu", params))
    message = str(info.value)
    assert message.startswith(f"load_bus at {dev['path']}: no device with unit id 7 answers (")
    assert "after 3 attempts" in message and "stays silent" in message
    assert "device_id = 7" in message and f"baud rate {dev['baudrate']}, parity N" in message
    time.sleep(0.4)  # the null modem has nothing left in flight
    supply = KINDS["riden-rd60xx"].open(
        OpenSpec("load_bus", "modbus-rtu", params | {"device_id": 1})
    )
    try:
        assert supply.identify().model == "RD6006"
    finally:
        supply.close()


def test_a_device_failure_is_still_a_device_failure(
    devices: dict[str, Any], cage: SimulatedCage
) -> None:
    dev = devices["coil_z"]
    link = ModbusLink(name="coil_z", host="127.0.0.1", port=dev["port"], timeout_s=0.5)
    faults = cage.faults["coil_z"]
    try:
        assert len(link.read_registers(0, 1)) == 1
        faults.exception_code = 4
        try:
            with pytest.raises(DeviceRefusedError) as info:
                link.read_registers(0, 1)
        finally:
            faults.exception_code = 0
    finally:
        link.close()
    assert not isinstance(info.value, DeviceAbsentError)
    assert "Modbus exception 4 (server device failure); the device failed" in str(info.value)
    assert "unit id" not in str(info.value)
