"""The simulated Riden RD60xx as the published tables and the makers' register lists define it:
the model table, the RD6012P's two current ranges, power, representable protection defaults,
protection that trips when lowered below the output, clock/settings/presets, and echo replies.
Each test drives the simulator over loopback Modbus TCP."""

from __future__ import annotations

import re
import socket
import struct
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient

from drivers.psu.riden import RidenSupply
from drivers.transport.modbus import ModbusLink
from sim.cage import SimulatedCage
from sim.config import load_config
from sim.physics import RIDEN_MODELS, riden_model
from tests.drivers.riden_published import NOT_RIDEN_IDS, PUBLISHED

pytestmark = pytest.mark.realtime


def test_the_simulators_model_table_is_the_published_one() -> None:
    sim_ids = {i for ids in RIDEN_MODELS for i in ids}
    assert sim_ids == {i for p in PUBLISHED for i in p.ids}
    for pub in PUBLISHED:
        for model_id in pub.ids:
            spec = riden_model(model_id)
            assert (spec.name, spec.v_per_count, spec.w_per_count) == (
                pub.name, pub.v_per_count, pub.w_per_count)  # fmt: skip
            assert (spec.a_per_count, spec.i_max_a) == (pub.a_per_count, pub.i_max_a)
    for model_id in NOT_RIDEN_IDS:
        with pytest.raises(ValueError, match=rf"unknown Riden model id {model_id}"):
            riden_model(model_id)


@pytest.fixture(scope="module")
def p_cage(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimulatedCage]:
    """coil_x an RD6012P in the 6 A range, coil_z one in the 12 A range (both Modbus TCP)."""
    text = Path(load_config().source).read_text()
    for axis, current_range in (("x", 0), ("z", 1)):
        text = re.sub(
            rf'model_id = \d+[^\n]*\naxis = "{axis}"',
            f'model_id = 60125\ncurrent_range = {current_range}\naxis = "{axis}"',
            text,
        )
    path = tmp_path_factory.mktemp("rd6012p") / "cage.toml"
    path.write_text(text)
    cage = SimulatedCage(load_config(path))
    cage.start()
    yield cage
    cage.stop()


def endpoint(cage: SimulatedCage, name: str) -> tuple[int, int]:
    dev = cage.endpoints_document()["devices"][name]
    assert dev["protocol"] == "modbus-tcp"
    return int(dev["port"]), int(dev["device_id"])


def raw(cage: SimulatedCage, name: str) -> ModbusTcpClient:
    port, _ = endpoint(cage, name)
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2.0)
    assert client.connect()
    return client


def regs(client: ModbusTcpClient, address: int, count: int = 1) -> list[int]:
    rr = client.read_holding_registers(address, count=count, device_id=1)
    assert not rr.isError(), rr
    return list(rr.registers)


@pytest.mark.parametrize(("name", "a_counts"), [("coil_x", 10000), ("coil_z", 1000)])
def test_rd6012p_5v_1a_in_each_range(p_cage: SimulatedCage, name: str, a_counts: int) -> None:
    port, device_id = endpoint(p_cage, name)
    link = ModbusLink(name=name, host="127.0.0.1", port=port, device_id=device_id, timeout_s=2.0)
    supply = RidenSupply(link, name=name)
    client = raw(p_cage, name)
    try:
        assert supply.model == "RD6012P"
        supply.set_voltage(5.0)
        supply.set_current(1.0)
        assert regs(client, 8, 2) == [5000, a_counts]
        r = supply.read()
        assert (r.v_set_v, r.i_set_a) == (5.0, 1.0)
    finally:
        supply.safe()
        supply.close()
        client.close()


def test_power_protection_defaults_and_trips(p_cage: SimulatedCage) -> None:
    client = raw(p_cage, "coil_x")  # RD6012P, 6 A range: 1 mV, 0.1 mA, 1 mW per count
    supply = p_cage.physics.supplies["coil_x"]
    try:
        ovp, ocp = regs(client, 82, 2)
        assert (ovp * 0.001, ocp * 0.0001) == pytest.approx((62.0, 6.2))  # not 66 V wrapped
        for reg, value in ((8, 2000), (9, 10000), (18, 1)):  # 2 V into ~4 ohm: CV, 0.5 A
            assert not client.write_register(reg, value, device_id=1).isError()
        time.sleep(0.3)  # > 10 L/R
        r = regs(client, 8, 13)
        v_out, i_out, p = r[2] * 0.001, r[3] * 0.0001, ((r[4] << 16) | r[5]) * 0.001
        assert p == pytest.approx(v_out * i_out, abs=0.002) and p > 0.5
        assert regs(client, 80, 2) == [2000, 10000]  # M0 mirrors the active set
        # OCP lowered below the output current trips at once, without another set-point write
        assert not client.write_register(83, 1000, device_id=1).isError()  # 0.1 A
        assert regs(client, 16, 3) == [2, 0, 0] and not supply.output
        assert not client.write_register(83, 62000, device_id=1).isError()
        assert not client.write_register(18, 1, device_id=1).isError()
        assert not client.write_register(82, 1500, device_id=1).isError()  # OVP 1.5 V < 2 V
        assert regs(client, 16, 3) == [1, 0, 0] and not supply.output
    finally:
        client.write_register(82, 62000, device_id=1)
        client.write_register(18, 0, device_id=1)
        client.close()


def test_clock_settings_and_presets_are_kept(p_cage: SimulatedCage) -> None:
    client = raw(p_cage, "coil_x")
    try:
        clock = [2026, 11, 25, 21, 30, 5]
        assert not client.write_registers(48, clock, device_id=1).isError()
        assert regs(client, 48, 6) == clock
        assert not client.write_register(72, 3, device_id=1).isError()  # backlight
        assert not client.write_registers(84, [1200, 5000, 62000, 62000], device_id=1).isError()
        assert regs(client, 72) == [3] and regs(client, 84, 4) == [1200, 5000, 62000, 62000]
        rr = client.write_register(55, 1, device_id=1)  # calibration: never written by us
        assert rr.isError() and rr.exception_code == 2
    finally:
        client.close()


def write_single(port: int, address: int, value: int, tid: int) -> tuple[bytes, bytes]:
    """One Modbus TCP Write Single Register request and the raw reply bytes."""
    request = struct.pack(">HHHBBHH", tid, 0, 6, 1, 6, address, value)
    with socket.create_connection(("127.0.0.1", port), timeout=2.0) as sock:
        sock.sendall(request)
        reply = b""
        while len(reply) < 12:
            chunk = sock.recv(12 - len(reply))
            if not chunk:
                break
            reply += chunk
    return request, reply


def test_every_write_single_register_reply_is_an_echo(p_cage: SimulatedCage) -> None:
    port, _ = endpoint(p_cage, "coil_x")
    writes = [(8, 3000), (9, 5000), (82, 2000), (18, 1),  # output on with OVP 2 V < 3 V: trips
              (18, 0), (82, 62000), (18, 1), (83, 1),  # OCP 0.1 mA below the output: trips
              (83, 62000), (18, 0), (48, 2026), (66, 1), (72, 5), (19, 0), (15, 0),
              (100, 1234), (20, 1), (20, 0), (9, 0), (8, 0)]  # fmt: skip
    for tid, (address, value) in enumerate(writes, 1):
        request, reply = write_single(port, address, value, tid)
        assert reply == request, f"register {address} = {value}: {reply.hex(' ')}"


@pytest.mark.parametrize(("lines", "message"), [
    ("model_id = 60209", r"supply 'coil_x': unknown Riden model id 60209; known: RD6006 60060-60064"),
    ("model_id = 60065\ncurrent_range = 1",
     r"supply 'coil_x': current_range 1 does not exist on the RD6006P; use 0-0"),
])  # fmt: skip
def test_a_wrong_model_in_the_cage_file_is_one_line(
    tmp_path: Path, lines: str, message: str
) -> None:
    from sim.cage import SimulatedCage as Cage
    from sim.config import SimConfigError

    text = Path(load_config().source).read_text()
    text = re.sub(r'model_id = \d+[^\n]*\naxis = "x"', f'{lines}\naxis = "x"', text)
    path = tmp_path / "cage.toml"
    path.write_text(text)
    with pytest.raises(SimConfigError, match=message) as info:
        Cage(load_config(path))
    assert "\n" not in str(info.value)
