"""A wrong Modbus device id, byte by byte: an RTU device with another id stays silent, a Modbus TCP
gateway answers exception 10 or 11. The driver names the id and says where to look; a device's
own exceptions read as words with a hint, and are never mistaken for a wrong id."""

from __future__ import annotations

import contextlib
import socket
import threading

import pytest

from drivers.errors import (
    DeviceAbsentError,
    DeviceRefusedError,
    DeviceTimeoutError,
)
from drivers.transport.modbus import EXCEPTIONS, ModbusLink
from tests.drivers.scripted import Exchange, ScriptedSerialPeer, ScriptedTcpPeer, rtu

READ_0 = "03 00 00 00 01"


def rtu_link(peer: ScriptedSerialPeer, device_id: int, retries: int = 1) -> ModbusLink:
    return ModbusLink(name="coil_y", path=peer.path, baudrate=9600, device_id=device_id,
                      timeout_s=0.3, retries=retries)  # fmt: skip


def tcp_link(peer: ScriptedTcpPeer, device_id: int) -> ModbusLink:
    return ModbusLink(name="coil_x", host="127.0.0.1", port=peer.port, device_id=device_id,
                      timeout_s=0.5, retries=2)  # fmt: skip


def test_rtu_silence_on_a_fresh_link_names_the_device_id() -> None:
    request = rtu(f"07 {READ_0}")  # the driver asks id 7; the supply on the line has id 1
    peer = ScriptedSerialPeer([Exchange(request, b""), Exchange(request, b"")])
    link = rtu_link(peer, 7)
    try:
        with pytest.raises(DeviceTimeoutError) as info:
            link.read_registers(0, 1)
    finally:
        link.close()
        peer.close()
    assert peer.mismatches == []
    message = str(info.value)
    assert message.startswith(f"coil_y at {peer.path}: no device with unit id 7 answers (")
    assert "after 2 attempts" in message and "stays silent when the id is not its own" in message
    assert "device_id = 7" in message and "menu or DIP switches" in message
    assert "baud rate 9600, parity N" in message
    assert "\n" not in message


def test_rtu_silence_after_replies_is_not_blamed_on_the_id() -> None:
    request = rtu(f"01 {READ_0}")
    peer = ScriptedSerialPeer([
        Exchange(request, rtu("01 03 02 EA A1")),
        Exchange(request, b""),
        Exchange(request, b""),
    ])  # fmt: skip
    link = rtu_link(peer, 1)
    try:
        assert link.read_registers(0, 1) == [60065]
        with pytest.raises(
            DeviceTimeoutError, match=r"after 2 attempts; it answered before"
        ) as info:
            link.read_registers(0, 1)
    finally:
        link.close()
        peer.close()
    assert peer.mismatches == []
    assert "unit id" not in str(info.value)


@pytest.mark.parametrize(
    ("code", "words"),
    [
        (0x0B, "gateway target device failed to respond"),
        (0x0A, "gateway path unavailable"),
    ],
)
def test_tcp_gateway_exception_on_a_fresh_link_is_a_wrong_id(code: int, words: str) -> None:
    peer = ScriptedTcpPeer([(bytes.fromhex(f"07 {READ_0}"), bytes([7, 0x83, code]))])
    link = tcp_link(peer, 7)
    try:
        with pytest.raises(DeviceAbsentError) as info:  # answered at once: never retried
            link.read_registers(0, 1)
    finally:
        link.close()
        peer.close()
    assert peer.mismatches == []
    assert isinstance(info.value, DeviceRefusedError)  # something answered at HOST:PORT
    message = str(info.value)
    assert message.startswith(
        f"coil_x at 127.0.0.1:{peer.port}: no device with unit id 7 answers (the gateway replied"
        f" Modbus exception {code}, {words}, to reading 1 register(s) at 0); check the device's"
        " Modbus address in the rig configuration (device_id = 7)"
    )
    assert "device failure" not in message


def test_tcp_target_that_stops_answering_is_not_blamed_on_the_id() -> None:
    peer = ScriptedTcpPeer([
        (bytes.fromhex(f"01 {READ_0}"), bytes.fromhex("01 03 02 EA A1")),
        (bytes.fromhex(f"01 {READ_0}"), bytes.fromhex("01 83 0B")),
    ])  # fmt: skip
    link = tcp_link(peer, 1)
    try:
        assert link.read_registers(0, 1) == [60065]
        with pytest.raises(
            DeviceAbsentError, match=r"unit id 1 stopped answering behind the gateway"
        ):
            link.read_registers(0, 1)
    finally:
        link.close()
        peer.close()
    assert peer.mismatches == []


def test_tcp_silence_on_a_fresh_link_mentions_the_unit_id() -> None:
    """A device that ignores a unit id it does not serve (or a gateway slower than our timeout)."""
    server = socket.create_server(("127.0.0.1", 0))
    received: list[bytes] = []

    def listen_only() -> None:
        conn, _ = server.accept()
        with conn:
            conn.settimeout(3.0)
            with contextlib.suppress(OSError):
                while data := conn.recv(256):
                    received.append(data)

    thread = threading.Thread(target=listen_only, daemon=True)
    thread.start()
    port = server.getsockname()[1]
    link = ModbusLink(name="coil_x", host="127.0.0.1", port=port, device_id=7, timeout_s=0.3,
                      retries=0)  # fmt: skip
    try:
        with pytest.raises(DeviceTimeoutError) as info:
            link.read_registers(0, 1)
    finally:
        link.close()
        thread.join(5)
        server.close()
    assert b"".join(received)[6:] == bytes.fromhex(f"07 {READ_0}")  # MBAP unit id 7, then the PDU
    message = str(info.value)
    assert message.startswith(
        f"coil_x at 127.0.0.1:{port}: no reply to reading 1 register(s) at 0 after 1 attempt;"
    )
    assert "may ignore a request for a unit id it does not serve" in message
    assert "device_id = 7" in message


@pytest.mark.parametrize(
    ("code", "words", "hint"),
    [
        (1, "illegal function", "does not offer this request"),
        (2, "illegal data address", "no such register"),
        (3, "illegal data value", "refused the value"),
        (4, "server device failure", "look at its display"),
        (5, "acknowledge", "needs long"),
        (6, "server device busy", "busy with a long operation"),
        (8, "memory parity error", "memory failed"),
        (12, "not a standard code", "the device's manual"),
    ],
)
def test_device_exceptions_read_as_words_with_a_hint(code: int, words: str, hint: str) -> None:
    peer = ScriptedTcpPeer([(bytes.fromhex("01 06 00 08 2E E0"), bytes([1, 0x86, code]))])
    link = tcp_link(peer, 1)
    try:
        with pytest.raises(DeviceRefusedError) as info:
            link.write_register(8, 12000)
    finally:
        link.close()
        peer.close()
    assert peer.mismatches == []
    assert not isinstance(info.value, DeviceAbsentError)  # the device answered: its id is right
    message = str(info.value)
    assert message.startswith(
        f"coil_x at 127.0.0.1:{peer.port} refused writing 12000 to register 8:"
        f" Modbus exception {code} ({words}); "
    )
    assert hint in message and "unit id" not in message


def test_every_standard_exception_code_has_words_and_a_hint() -> None:
    assert set(EXCEPTIONS) == {1, 2, 3, 4, 5, 6, 8, 10, 11}
    assert all(name and "; " not in name and hint for name, hint in EXCEPTIONS.values())
