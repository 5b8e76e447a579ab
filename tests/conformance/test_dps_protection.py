"""The simulated RDTech DPS5005 and DPS5015 answer the protection queries other people's clients
send, at the scales of the maker's table ("DPS5005 communication protocol V1.2": the active
preset M0 at 0x50-0x57, S-OVP V x 100, S-OCP A x 1000 on the 5 A models and x 100 on the 15/20 A
ones, S-OPP W x 10). No DPS client library is on PyPI, so the requests are sent by an independent
Modbus master (minimalmodbus 2.1) exactly as the clients send them: libsigrok's rdtech-dps driver
reads S-OVP and S-OCP as two registers from 0x52 and writes each with function 16; TheHWcave's
DPS5005-control writes them with function 06. Before issue 53 the first read answered
exception 2."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

minimalmodbus = pytest.importorskip("minimalmodbus", reason="minimalmodbus is a dev dependency")

from drivers.psu.regmap_device import MappedSupply  # noqa: E402
from drivers.transport.modbus import ModbusLink  # noqa: E402
from regmaps import load_map  # noqa: E402
from sim.cage import SimulatedCage  # noqa: E402
from tests.conformance.simcage import cage_with, endpoint  # noqa: E402

pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def cage(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimulatedCage]:
    swaps = {"coil_y": 'kind = "regmap"\nregmap = "dps5005"\nbaudrate = 9600',
             "load_bus": 'kind = "regmap"\nregmap = "dps5015"\nbaudrate = 9600'}  # fmt: skip
    with cage_with(tmp_path_factory.mktemp("dps"), swaps) as c:
        yield c


def master(path: str) -> minimalmodbus.Instrument:
    inst = minimalmodbus.Instrument(path, 1)
    inst.serial.baudrate = 9600
    inst.serial.timeout = 0.5
    return inst


def rig_supply(path: str, regmap: str) -> MappedSupply:
    link = ModbusLink(name=regmap, path=path, baudrate=9600, timeout_s=1.0, retries=2)
    return MappedSupply(link, load_map(regmap), name=regmap)


def test_libsigroks_ovp_ocp_query_and_writes_on_the_dps5005(cage: SimulatedCage) -> None:
    path = endpoint(cage, "coil_y")["path"]
    inst = master(path)
    try:
        ovp, ocp = inst.read_registers(0x52, 2)  # what failed with exception 2 before
        assert (ovp, ocp) == (5500, 5500)  # the simulator's 55.00 V, 5.500 A at power-on
        inst.write_register(0x52, 1320, functioncode=16)  # 13.20 V
        inst.write_register(0x53, 1600, functioncode=16)  # 1.600 A
        assert inst.read_registers(0x52, 2) == [1320, 1600]
        assert inst.read_register(0x54) == 2500  # S-OPP 250.0 W
    finally:
        inst.serial.close()
    supply = rig_supply(path, "dps5005")
    try:
        levels = {p.kind: (p.value, p.register) for p in supply.protection_levels()}
        assert levels == {"OVP": (13.2, "register 's_ovp' (0x0052)"),
                          "OCP": (1.6, "register 's_ocp' (0x0053)"),
                          "OPP": (250.0, "register 's_opp' (0x0054)")}  # fmt: skip
    finally:
        supply.set_protection_levels(ovp_v=55.0, ocp_a=5.5)  # as at power-on, for the others
        supply.close()


def test_the_active_preset_mirrors_the_set_points_and_trips(cage: SimulatedCage) -> None:
    path = endpoint(cage, "coil_y")["path"]
    supply = rig_supply(path, "dps5005")
    try:
        supply.set_protection_levels(ovp_v=13.2, ocp_a=3.0)
        supply.set_voltage(12.0)
        supply.set_current(1.5)
    finally:
        supply.close()
    inst = master(path)
    try:
        assert inst.read_registers(0x50, 8)[:4] == [1200, 1500, 1320, 3000]  # U, I, OVP, OCP
        inst.write_register(0x51, 2000)  # M0 I-SET 2.000 A by function 06: 0x01 follows
        assert inst.read_register(0x01) == 2000
        inst.write_register(0x09, 1)  # output on: 12 V into 4.2 ohm wants 2.86 A, CC at 2 A
        time.sleep(0.2)
        inst.write_register(0x53, 1000)  # S-OCP 1.000 A, below the output: trips at once
        assert (inst.read_register(0x07), inst.read_register(0x09)) == (2, 0)  # OCP, off
    finally:
        inst.write_registers(0x52, [5500, 5500])  # as at power-on, for the others
        inst.serial.close()


def test_the_dps5015_counts_ocp_in_10_ma(cage: SimulatedCage) -> None:
    path = endpoint(cage, "load_bus")["path"]
    supply = rig_supply(path, "dps5015")
    try:
        levels = supply.set_protection_levels(ovp_v=24.5, ocp_a=12.34, opp_w=600.0)
        assert [(p.kind, p.value) for p in levels] == [("OVP", 24.5), ("OCP", 12.34),
                                                      ("OPP", 600.0)]  # fmt: skip
    finally:
        supply.close()
    inst = master(path)
    try:  # TheHWcave's function-06 read-back of the same registers: the table's counts
        assert inst.read_registers(0x52, 3) == [2450, 1234, 6000]
    finally:
        inst.serial.close()
