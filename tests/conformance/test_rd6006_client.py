"""The simulated Riden RD6006 and RD6006P driven by an independent client, rd6006 0.2 (PyPI;
github.com/Baldanos/rd6006; minimalmodbus over Modbus RTU on a pseudo-terminal).

rd6006 0.2 scales by ``model id // 10``: 6012/6018/6024 as V/100 A/100, everything else as
V/100 A/1000. That is right for the RD6006 and wrong for the P models: the RD6006P (60065) counts
1 mV and 0.1 mA (ShayBox/Riden riden.py, libsigrok rdtech-dps, riden-dongle), so the library
reads its volts and amps 10x high and writes 10x low. On the RD6006P the scaled values are
therefore checked against the published tables through the library's raw register access, and
the library's error is asserted as documented (docs/devices.md, "disagreements")."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

rd6006 = pytest.importorskip("rd6006", reason="rd6006 is a dev dependency")

from drivers.psu.riden import RidenSupply  # noqa: E402
from drivers.transport.modbus import ModbusLink  # noqa: E402
from sim.cage import SimulatedCage  # noqa: E402
from tests.conformance.simcage import cage_with, endpoint  # noqa: E402

pytestmark = pytest.mark.realtime

LOAD_OHM = 6.0  # load_bus of the default cage (an RD6006 into a resistor)


@pytest.fixture(scope="module")
def cage(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimulatedCage]:
    with cage_with(tmp_path_factory.mktemp("rd6006"), {}) as c:  # coil_y RD6006P, load_bus RD6006
        yield c


def client(path: str) -> object:
    psu = rd6006.RD6006(path)
    psu.instrument.serial.timeout = 0.5  # a busy machine: minimalmodbus' 0.05 s is tight
    return psu


def rig_supply(path: str, name: str) -> RidenSupply:
    link = ModbusLink(name=name, path=path, baudrate=115200, timeout_s=1.0, retries=2)
    return RidenSupply(link, name=name)


def test_rd6006_identification_set_points_read_back_and_power(cage: SimulatedCage) -> None:
    path = endpoint(cage, "load_bus")["path"]
    psu = client(path)
    try:
        assert psu.type == 6006 and psu.sn == 12345 and psu.fw == 1.4
        psu.voltage = 12.0
        psu.current = 1.5
        psu.enable = 1
        time.sleep(0.1)
        assert (psu.voltage, psu.current, psu.enable) == (12.0, 1.5, 1)
        # 12 V into 6 ohm wants 2 A > 1.5 A: constant current (register 17 = 1), V = I R = 9 V
        assert psu.meascurrent == pytest.approx(1.5, abs=0.001)
        assert psu.measvoltage == pytest.approx(1.5 * LOAD_OHM, abs=0.01)
        assert psu.measpower == pytest.approx(13.5, abs=0.02)  # W x 100 in registers 12-13
        assert psu.CVCC == 1 and psu.ocpovp == 0
        v, i, p = psu.measvoltage, psu.meascurrent, psu.measpower
    finally:
        psu.instrument.serial.close()
    supply = rig_supply(path, "load_bus")
    try:
        assert supply.identify().model == "RD6006"
        r = supply.read()
        assert (r.v_set_v, r.i_set_a, r.output_on, r.constant_current) == (12.0, 1.5, True, True)
        assert (r.v_out_v, r.i_out_a, r.power_w) == pytest.approx((v, i, p), abs=0.011)
    finally:
        supply.safe()
        supply.close()


def test_rd6006_protection_trips_when_lowered_and_reads_back(cage: SimulatedCage) -> None:
    path = endpoint(cage, "load_bus")["path"]
    psu = client(path)
    try:
        assert (psu.voltage_protection, psu.current_protection) == (62.0, 6.2)
        psu.voltage = 12.0
        psu.current = 1.5
        psu.enable = 1
        time.sleep(0.1)
        psu.current_protection = 1.0  # below the 1.5 A output: trips at once
        assert (psu.ocpovp, psu.enable) == (2, 0)
        psu.current_protection = 6.2
        psu.enable = 1
        psu.voltage_protection = 8.0  # below the 12 V set-point
        assert (psu.ocpovp, psu.enable) == (1, 0)
        psu.voltage_protection = 62.0
        psu.date = psu.date  # the clock (48-50) and the backlight (72) take writes
        psu.backlight = 3
        assert psu.backlight == 3
    finally:
        psu.enable = 0
        psu.instrument.serial.close()


def test_rd6006p_the_library_is_10x_off_the_published_scales(cage: SimulatedCage) -> None:
    path = endpoint(cage, "coil_y")["path"]
    psu = client(path)
    try:
        assert psu._read_register(0) == 60065  # RD6006P
        assert (psu.voltres, psu.ampres) == (100, 1000)  # the library's guess: RD6006 scales
        # raw registers with the published scales: 1 mV, 0.1 mA, 1 mW per count
        psu._write_register(8, 5000)  # 5.000 V
        psu._write_register(9, 10000)  # 1.0000 A
        psu._write_register(18, 1)
        time.sleep(0.3)  # > 10 L/R
        assert psu.voltage == 50.0  # the library reads 5.000 V as 50 V: its error, documented
        v_counts, i_counts = psu._read_register(10), psu._read_register(11)
        assert i_counts * 0.0001 == pytest.approx(1.0, abs=0.0005)  # CC: 5 V / 4.2 ohm > 1 A
        assert v_counts * 0.001 == pytest.approx(4.2, abs=0.005)
        power = (psu._read_register(12) << 16 | psu._read_register(13)) * 0.001
        assert power == pytest.approx(4.2, abs=0.01)
        assert (psu._read_register(82), psu._read_register(83)) == (62000, 62000)  # 62 V, 6.2 A
    finally:
        psu.instrument.serial.close()
    supply = rig_supply(path, "coil_y")  # the rig reads the same output (then switches it off)
    try:
        r = supply.read()
        assert (r.v_set_v, r.i_set_a) == (5.0, 1.0)
        assert r.output_on
        assert (r.v_out_v, r.i_out_a) == pytest.approx(
            (v_counts * 0.001, i_counts * 0.0001), abs=2e-3
        )
    finally:
        supply.safe()
        supply.close()


@pytest.fixture(scope="module")
def rd6018(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimulatedCage]:
    swap = {"coil_y": 'kind = "riden-rd60xx"\nmodel_id = 60181'}  # an RD6018 on the 4.2 ohm coil
    with cage_with(tmp_path_factory.mktemp("rd6018"), swap) as c:
        yield c


def test_power_beyond_655_w_is_two_registers(rd6018: SimulatedCage) -> None:
    """Registers 12-13 are one 32-bit power, high word first (docs/devices.md: a real RD6030
    read through register 13 alone wrapped at 655.36 W). rd6006's ``measpower`` reads them so;
    its ``status()`` prints register 13 alone, as libsigrok does."""
    path = endpoint(rd6018, "coil_y")["path"]
    psu = client(path)
    try:
        psu.voltage = 60.0
        psu.current = 14.0  # 60 V into 4.2 ohm wants 14.3 A: CC at 14 A, 58.8 V, 823.2 W
        psu.enable = 1
        time.sleep(0.3)  # > 10 L/R
        watts = 14.0 * 14.0 * 4.2
        high, low = psu._read_register(12), psu._read_register(13)
        assert high == 1 and (high << 16 | low) == pytest.approx(watts * 100, abs=30)
        assert psu.measpower == pytest.approx(watts, abs=0.3)  # 0.01 W a count
        # ESPHome's U_DWORD at 12 (read a moment later: the current moves by a count or so)
        assert psu.instrument.read_long(12) == pytest.approx(high << 16 | low, abs=30)
        assert low / 100 == pytest.approx(watts - 655.36, abs=0.3)  # register 13 alone: wrapped
    finally:
        psu.instrument.serial.close()
    supply = rig_supply(path, "coil_y")  # the output is still on: the rig reads it, then safe
    try:
        assert supply.read().power_w == pytest.approx(watts, abs=0.3)
    finally:
        supply.safe()
        supply.close()
