"""The real drivers on simulated wires, in simulated time (ADR 0038): a reply arrives when its
bytes have crossed the line, and a silent device times out after exactly its timeout (and its
retries) of simulated time, taking almost no wall time, beside two CPU hogs as on an idle
computer. Wall times are printed, never asserted."""

from __future__ import annotations

import inspect
import time

import pytest

import timebase
from drivers.errors import DeviceNotFoundError, DeviceTimeoutError
from drivers.transport import modbus, serial_port, tty_watch
from drivers.transport.modbus import ModbusLink, PatientSerialClient, SimulatedTcpClient
from drivers.transport.serial_port import SerialPort
from tests.drivers.wire_devices import Registers, cpu_hogs, serve_echo, serve_rtu, serve_tcp
from timebase.wires import PipeEnd, wires


def _report(what: str, sim_s: float, wall_s: float) -> None:
    print(f"{what}: {sim_s:.6f} s simulated, {wall_s:.4f} s of wall time")


def test_serial_port_reply_and_timeout_on_the_simulated_clock() -> None:
    wall0 = time.monotonic()
    with timebase.simulated():
        serve_echo("echo", baud=9600)
        port = SerialPort("simpipe://echo", 9600, timeout_s=0.5, name="echo")
        t0 = timebase.monotonic()
        port.write(b"abc\r")
        assert port.read_until(b"\r") == b"ABC\r"
        # 4 bytes there, 4 back, at 10 bits per byte and 9600 Bd
        assert timebase.monotonic() - t0 == pytest.approx(8 * 10 / 9600)
        t1 = timebase.monotonic()
        with pytest.raises(DeviceTimeoutError, match=r"within 0\.5 s"):
            port.read_until(b"\r")
        assert timebase.monotonic() - t1 == pytest.approx(0.5)
        port.close()
        assert tty_watch.tty_watch() is None  # no kernel terminal layer to watch in here
        assert serial_port.own_stall_s(10.0, 0.5) == 0.0
    _report("serial reply and timeout", 0.5 + 8 * 10 / 9600, time.monotonic() - wall0)


def test_a_silent_line_times_out_exactly_beside_cpu_hogs() -> None:
    with cpu_hogs(2):
        wall0 = time.monotonic()
        with timebase.simulated():
            serve_echo("mute", silent=True)
            port = SerialPort("simpipe://mute", 9600, timeout_s=0.5, name="mute")
            for _ in range(20):
                t0 = timebase.monotonic()
                port.write(b"*99P\r")
                with pytest.raises(DeviceTimeoutError):
                    port.read_exact(7)
                assert timebase.monotonic() - t0 == 0.5
            port.close()
            sim_s = timebase.monotonic()
        _report("20 serial timeouts of 0.5 s beside two CPU hogs", sim_s, time.monotonic() - wall0)
    assert sim_s == pytest.approx(10.0)


def test_modbus_rtu_reply_and_silence_beside_cpu_hogs() -> None:
    with cpu_hogs(2):
        wall0 = time.monotonic()
        with timebase.simulated():
            regs = Registers({10: 1234, 11: 5678})
            serve_rtu("psu", regs, baud=115200)
            link = ModbusLink(name="psu", path="simpipe://psu", baudrate=115200, timeout_s=0.5)
            assert isinstance(link._client, PatientSerialClient)
            t0 = timebase.monotonic()
            assert link.read_registers(10, 2) == [1234, 5678]
            # 8 bytes out, 9 back at 115200 Bd: the reply is taken once its last byte is in
            assert timebase.monotonic() - t0 == pytest.approx(17 * 10 / 115200)
            link.write_register(20, 7)
            assert regs.values[20] == 7
            regs.silent = True
            t1 = timebase.monotonic()
            with pytest.raises(DeviceTimeoutError, match="after 3 attempts"):
                link.read_registers(10, 2)
            # the line's t3.5 of silence after the last reply, then 0.5 s x 3 attempts
            assert timebase.monotonic() - t1 == pytest.approx(modbus.rtu_silence_s(115200) + 1.5)
            assert len([t for t, _ in regs.requests if t >= t1]) == 3
            link.close()
            sim_s = timebase.monotonic()
        _report("Modbus RTU beside two CPU hogs", sim_s, time.monotonic() - wall0)


def test_a_late_rtu_reply_answers_the_retry() -> None:
    """A reply that comes after the timeout is taken by the retry of the same request; the
    device's answer to the repeated request is recognized as stale on the next one."""
    with timebase.simulated():
        regs = Registers({10: 1, 11: 2, 12: 3}, delay_s=0.6)
        serve_rtu("slow", regs, baud=115200)
        link = ModbusLink(name="slow", path="simpipe://slow", baudrate=115200, timeout_s=0.5)
        t0 = timebase.monotonic()
        assert link.read_registers(10, 2) == [1, 2]
        assert timebase.monotonic() - t0 == pytest.approx(0.6 + 17 * 10 / 115200)
        regs.delay_s = 0.0
        assert link.read_registers(10, 3) == [1, 2, 3]
        assert link.stale_replies == 1  # the answer to the repeated request, recognized
        link.close()


def test_modbus_tcp_reply_silence_and_refusal_beside_cpu_hogs() -> None:
    with cpu_hogs(2):
        wall0 = time.monotonic()
        with timebase.simulated():
            regs = Registers({0: 42})
            port = serve_tcp(regs, port=1502)
            link = ModbusLink(name="load", host="localhost", port=port, timeout_s=0.5)
            assert isinstance(link._client, SimulatedTcpClient)
            t0 = timebase.monotonic()
            assert link.read_registers(0, 1) == [42]
            assert timebase.monotonic() == t0  # the simulated loopback has no latency
            regs.delay_s = 0.2
            assert link.read_registers(0, 1) == [42]
            assert timebase.monotonic() - t0 == pytest.approx(0.2)
            regs.silent = True
            t1 = timebase.monotonic()
            with pytest.raises(DeviceTimeoutError, match="after 3 attempts"):
                link.read_registers(0, 1)
            assert timebase.monotonic() - t1 == pytest.approx(1.5)
            link.close()
            with pytest.raises(DeviceNotFoundError, match="cannot connect"):
                ModbusLink(name="none", host="127.0.0.1", port=port + 1, timeout_s=0.5)
            sim_s = timebase.monotonic()
        _report("Modbus TCP beside two CPU hogs", sim_s, time.monotonic() - wall0)


def test_a_tcp_server_that_hangs_up_is_a_lost_connection() -> None:
    with timebase.simulated():
        ends: list[PipeEnd] = []
        port = wires().listen("127.0.0.1", 0, ends.append)
        link = ModbusLink(name="gw", host="127.0.0.1", port=port, timeout_s=0.5, retries=0)
        ends[0].close()
        with pytest.raises(DeviceNotFoundError, match="connection lost"):
            link.read_registers(0, 1)
        link.close()


def test_pymodbus_sync_deadline_and_lock_are_on_the_clock() -> None:
    """The pinned pymodbus' own timing of a synchronous request answers to timebase."""
    from pymodbus.transaction import transaction

    assert "monotonic()" in inspect.getsource(transaction.TransactionManager.sync_get_response)
    assert transaction.monotonic is timebase.monotonic  # type: ignore[attr-defined]
    with timebase.simulated():
        client = PatientSerialClient("simpipe://x", timeout=0.5, retries=0)
        assert type(client.transaction._sync_lock).__name__ == "SimRLock"
    assert modbus.pymodbus_transaction is transaction


def test_a_simulated_line_cannot_be_opened_on_the_wall_clock() -> None:
    with pytest.raises(DeviceNotFoundError, match="only in the simulated time"):
        SerialPort("simpipe://coil_x", 9600, name="coil_x")
