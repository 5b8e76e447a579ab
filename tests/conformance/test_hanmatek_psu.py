"""The simulated Hanmatek HM310P driven by an independent client, hanmatek-psu 1.1.2 (PyPI;
gitlab.com/janoskut/hanmatek-psu; minimalmodbus over Modbus RTU on a pseudo-terminal): its
discovery finds the supply (model 3010 and class 0x4B50 = 19280), it sets and reads back
voltage, current, output, power and the protection levels, OVP and OCP trip as on the unit, and
the rig's driver reads the same values. The expected numbers are the register table's (V x 100,
A x 1000, power W x 1000, OPP W x 100, protection bits 1 OVP / 2 OCP / 4 OPP), not the
simulator's: the OEM table as a real HM310T confirmed it (github.com/joeyda3rd/hm310t: OPP
30000 = 300.00 W at power-on, every unlisted address reads 0). hanmatek-psu scales OPP by 1000
and so reads it 10x low (30.0 W): asserted as its error, the raw words through its own
minimalmodbus instrument carry the table's scale."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

hanmatek = pytest.importorskip("hanmatek", reason="hanmatek-psu is a dev dependency")

from drivers.psu.regmap_device import MappedSupply  # noqa: E402
from drivers.transport.modbus import ModbusLink  # noqa: E402
from regmaps import load_map  # noqa: E402
from sim.cage import SimulatedCage  # noqa: E402
from tests.conformance.simcage import cage_with, endpoint  # noqa: E402

pytestmark = pytest.mark.realtime

RESISTANCE_OHM = 4.2  # coil_y of the default cage


@pytest.fixture(scope="module")
def cage(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimulatedCage]:
    lines = 'kind = "regmap"\nregmap = "hm310p"\nbaudrate = 9600'
    with cage_with(tmp_path_factory.mktemp("hm310p"), {"coil_y": lines}) as c:
        yield c


def client(path: str) -> object:
    """hanmatek-psu's own discovery on the pseudo-terminal (one port, address 1)."""
    found = hanmatek.HM3xxP.discover([path])
    assert len(found) == 1, "hanmatek-psu's discovery does not find the simulated HM310P"
    psu = found[0]
    psu.instrument.serial.timeout = 0.5  # a busy machine: the library's 0.1 s is tight
    return psu


def rig_supply(path: str) -> MappedSupply:
    link = ModbusLink(name="coil_y", path=path, baudrate=9600, timeout_s=1.0, retries=2)
    return MappedSupply(link, load_map("hm310p"), name="coil_y")


def test_discovery_identification_set_points_and_read_back(cage: SimulatedCage) -> None:
    path = endpoint(cage, "coil_y")["path"]
    psu = client(path)
    try:
        assert psu.info() == "KP3010"  # class 0x4B50 as two characters, then the model
        assert psu.read("decimals") == 0x0233
        psu.write("voltage:set", 12.0)
        psu.write("current:set", 2.5)
        psu.write("output", True)
        time.sleep(0.3)  # > 10 L/R of the coil
        assert psu.read("voltage:set") == pytest.approx(12.0)
        assert psu.read("current:set") == pytest.approx(2.5)
        assert psu.read("output") is True
        # 12 V into 4.2 ohm wants 2.86 A > 2.5 A: constant current, V = I R
        v, i, p = psu.read("voltage"), psu.read("current"), psu.read("power")
        assert i == pytest.approx(2.5, abs=0.002)
        assert v == pytest.approx(2.5 * RESISTANCE_OHM, abs=0.011)
        assert p == pytest.approx(v * i, abs=0.03) and p > 25.0
        assert psu.read("protection") == 0
    finally:
        psu.instrument.serial.close()
    supply = rig_supply(path)
    try:
        assert supply.identify().model == "Hanmatek HM310P"
        r = supply.read()
        assert (r.v_set_v, r.i_set_a, r.output_on, r.protection) == (12.0, 2.5, True, "")
        assert (r.v_out_v, r.i_out_a) == pytest.approx((v, i), abs=0.011)
        assert r.power_w == pytest.approx(p, abs=0.03)
    finally:
        supply.safe()
        supply.close()


@pytest.mark.parametrize(("level", "value", "bit", "name"), [
    ("ocp", 1.0, 2, "OCP"),  # OCP 1 A below a 2.5 A output
    ("ovp", 5.0, 1, "OVP"),  # OVP 5 V below a 12 V set-point
])  # fmt: skip
def test_lowered_protection_trips_at_once(
    cage: SimulatedCage, level: str, value: float, bit: int, name: str
) -> None:
    path = endpoint(cage, "coil_y")["path"]
    psu = client(path)
    try:
        defaults = psu.read("ovp"), psu.read("ocp")
        assert defaults == pytest.approx((33.0, 11.0))  # representable, above the 30 V / 10 A range
        psu.write("voltage:set", 12.0)
        psu.write("current:set", 2.5)
        psu.write("output", True)
        time.sleep(0.2)
        psu.write(level, value)  # no set-point write after it
        assert psu.read(level) == pytest.approx(value)
        assert psu.read("protection") == bit and psu.read("output") is False
    finally:
        psu.write(level, defaults[0] if level == "ovp" else defaults[1])
        psu.instrument.serial.close()
    supply = rig_supply(path)
    try:
        assert supply.read().protection == name
        supply.set_output(True)  # enabling again clears the latch
        assert supply.read().protection == ""
    finally:
        supply.safe()
        supply.close()


def test_the_registers_real_units_have(cage: SimulatedCage) -> None:
    psu = client(endpoint(cage, "coil_y")["path"])
    try:
        psu.write("m1:voltage", 5.0)
        psu.write("m1:current", 1.234)
        assert (psu.read("m1:voltage"), psu.read("m1:current")) == pytest.approx((5.0, 1.234))
        psu.write("timespan", 7)
        assert psu.read("timespan") == 7
        assert psu.read("addr") == 1 and psu.read("powercal") == 0.0
        assert psu.read("beep") is True and psu.read("powerstat") == 3
    finally:
        psu.instrument.serial.close()


def test_an_address_no_table_lists_reads_0_as_on_a_real_unit(cage: SimulatedCage) -> None:
    psu = client(endpoint(cage, "coil_y")["path"])
    try:  # the real HM310T's sweep: 0x0006-0x000F, 0x0024-0x002F and 0x00FF read 0
        assert psu.instrument.read_registers(0x0006, 10) == [0] * 10
        assert psu.instrument.read_register(0x00FF) == 0
        assert psu.instrument.read_register(0x0040) == 3200  # unlisted, read so on the unit
    finally:
        psu.instrument.serial.close()


def test_opp_at_the_tables_scale_set_read_back_and_tripping(cage: SimulatedCage) -> None:
    path = endpoint(cage, "coil_y")["path"]
    psu = client(path)
    try:
        assert psu.instrument.read_long(0x0022) == 30000  # power-on: 300.00 W (W x 100)
        assert psu.read("opp") == pytest.approx(30.0)  # hanmatek-psu's x 1000: 10x low
    finally:
        psu.instrument.serial.close()
    supply = rig_supply(path)
    try:
        assert {p.kind: p.value for p in supply.protection_levels()}["OPP"] == 300.0
        levels = supply.set_protection_levels(opp_w=150.0)
        assert [(p.kind, p.value) for p in levels if p.kind == "OPP"] == [("OPP", 150.0)]
    finally:
        supply.close()
    psu = client(path)
    try:
        assert psu.instrument.read_registers(0x0022, 2) == [0, 15000]  # high word first
        psu.instrument.write_long(0x0022, 1000)  # 10.00 W, below 2.5 A into 4.2 ohm (26 W)
        psu.write("voltage:set", 12.0)
        psu.write("current:set", 2.5)
        psu.write("output", True)
        assert psu.read("protection") == 4 and psu.read("output") is False  # bit 2: OPP
    finally:
        psu.instrument.write_long(0x0022, 30000)
        psu.instrument.serial.close()
    supply = rig_supply(path)
    try:
        assert supply.read().protection == "OPP"
    finally:
        supply.safe()
        supply.close()
