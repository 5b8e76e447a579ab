"""The Riden driver against register images built from the published model tables
(tests/drivers/riden_published.py), served over loopback Modbus TCP by a plain register image,
never by the project's simulator."""

from __future__ import annotations

import pytest

from drivers.errors import DeviceNotFoundError, LimitError
from drivers.psu.riden import MODELS, RidenSupply, riden_model
from drivers.transport.modbus import ModbusLink
from tests.drivers.register_image import RegisterImage
from tests.drivers.riden_published import NOT_RIDEN_IDS, PUBLISHED


def riden_image(model_id: int, **regs: int) -> RegisterImage:
    """Registers 0-120 of a Riden: the id, serial 12345, firmware 1.40, and ``regs`` by number."""
    image = {a: 0 for a in range(121)}
    image.update({0: model_id, 1: 0, 2: 12345, 3: 140})
    image.update({int(k.removeprefix("r")): v for k, v in regs.items()})
    return RegisterImage(image)


def open_riden(image: RegisterImage) -> RidenSupply:
    link = ModbusLink(name="coil_x", host="127.0.0.1", port=image.port, timeout_s=1.0, retries=0)
    return RidenSupply(link, name="coil_x")


ALL_IDS = [(p, i) for p in PUBLISHED for i in p.ids]


@pytest.mark.parametrize(("pub", "model_id"), ALL_IDS, ids=[f"{p.name}-{i}" for p, i in ALL_IDS])
def test_every_published_id_has_the_published_scales(pub: object, model_id: int) -> None:
    from tests.drivers.riden_published import Published

    assert isinstance(pub, Published)
    spec = riden_model(model_id)
    assert spec is not None, f"{model_id} ({pub.name}) is in the published tables"
    assert spec.name == pub.name
    assert (spec.v_per_count, spec.w_per_count) == (pub.v_per_count, pub.w_per_count)
    assert tuple(r.a_per_count for r in spec.ranges) == pub.a_per_count
    assert tuple(r.i_max_a for r in spec.ranges) == pub.i_max_a


def test_the_driver_knows_no_id_the_tables_do_not_list() -> None:
    published = {i for p in PUBLISHED for i in p.ids}
    assert {i for m in MODELS for i in m.ids} == published
    for model_id in NOT_RIDEN_IDS:
        assert riden_model(model_id) is None


@pytest.mark.parametrize("current_range", [0, 1])
def test_rd6012p_sets_and_reads_5v_1a_exactly_in_both_ranges(current_range: int) -> None:
    # the 6 A range counts 0.1 mA, the 12 A range 1 mA (register 20); V is 1 mV in both
    a_counts = 10000 if current_range == 0 else 1000
    power = 5000  # 5.000 W at 1 mW per count (32-bit, registers 12-13)
    with riden_image(60125, r20=current_range, r10=5000, r11=a_counts, r13=power, r18=1) as image:
        supply = open_riden(image)
        try:
            assert supply.identify().model == "RD6012P"
            assert supply.set_voltage(5.0) == 5.0
            assert supply.set_current(1.0) == 1.0
            assert image.writes == [(8, 5000), (9, a_counts)]
            r = supply.read()
            assert (r.v_set_v, r.i_set_a, r.v_out_v, r.i_out_a) == (5.0, 1.0, 5.0, 1.0)
            assert r.power_w == 5.0 and r.output_on
            assert supply.max_current_a == (6.0 if current_range == 0 else 12.0)
        finally:
            supply.close()


def test_rd6012p_follows_a_range_change_made_after_it_opened() -> None:
    with riden_image(60125, r20=1) as image:
        supply = open_riden(image)
        try:
            image.regs[20] = 0  # the front panel switches to the 6 A range
            assert supply.set_current(1.0) == 1.0
            assert image.writes == [(9, 10000)]  # 0.1 mA counts: not a silent 10x
            with pytest.raises(LimitError, match=r"7 A is outside 0-6 A"):
                supply.set_current(7.0)
            image.regs.update({20: 1, 9: 7000})
            assert supply.read().i_set_a == 7.0  # the range read in the same reply scales it
        finally:
            supply.close()


@pytest.mark.parametrize(("name", "model_id", "v_counts", "a_counts"), [
    ("RD6006", 60062, 500, 1000),
    ("RD6006P", 60065, 5000, 10000),
    ("RK6006", 60066, 500, 1000),
    ("RD6012", 60121, 500, 100),
    ("RD6018", 60181, 500, 100),
    ("RD6024", 60241, 500, 100),
    ("RD6030", 60301, 500, 100),
])  # fmt: skip
def test_5v_1a_in_each_models_counts(
    name: str, model_id: int, v_counts: int, a_counts: int
) -> None:
    with riden_image(model_id, r10=v_counts, r11=a_counts) as image:
        supply = open_riden(image)
        try:
            assert supply.model == name
            supply.set_voltage(5.0)
            supply.set_current(1.0)
            assert image.writes == [(8, v_counts), (9, a_counts)]
            r = supply.read()
            assert (r.v_out_v, r.i_out_a) == (5.0, 1.0)
            assert supply.set_voltage(12.34) == 12.34  # counts / counts-per-V: the decimal value
        finally:
            supply.close()


def test_an_unknown_model_id_is_refused_in_one_line() -> None:
    with riden_image(60209) as image:
        link = ModbusLink(name="coil_x", host="127.0.0.1", port=image.port, timeout_s=1.0)
        try:
            with pytest.raises(DeviceNotFoundError) as info:
                RidenSupply(link, name="coil_x")
        finally:
            link.close()
    message = str(info.value)
    assert "\n" not in message
    assert "model id 60209 is not a known Riden RD60xx" in message
    assert "RD6012P 60125-60129" in message and "check the device id" in message


def test_devices_scan_names_the_model_and_prints_an_unknown_ids_registers() -> None:
    from rig.bringup import scan, table

    with riden_image(60125, r20=1) as known, riden_image(60209) as unknown:
        found, strangers = scan(tcp=[("127.0.0.1", known.port), ("127.0.0.1", unknown.port)],
                                timeout_s=1.0)  # fmt: skip
    assert [(f.kind, f.model, f.serial) for f in found] == [("riden-rd60xx", "RD6012P", "12345")]
    assert [u.registers for u in strangers] == [(60209, 0, 12345, 140)]
    text = table(found, strangers)
    assert "RD6012P" in text
    assert "Riden-like model id 60209 not in the known RD60xx table" in text
    assert "(registers 0-3: 60209 0 12345 140)" in text


def test_a_configured_rd6012p_range_is_written_at_open_and_refused_elsewhere() -> None:
    with riden_image(60125, r20=0) as image:
        link = ModbusLink(name="coil_x", host="127.0.0.1", port=image.port, timeout_s=1.0)
        supply = RidenSupply(link, name="coil_x", current_range=1)
        try:
            assert image.writes == [(20, 1)] and supply.max_current_a == 12.0
            supply.set_current(1.0)
            assert image.writes[-1] == (9, 1000)
        finally:
            supply.close()
    with riden_image(60065) as image:
        link = ModbusLink(name="coil_x", host="127.0.0.1", port=image.port, timeout_s=1.0)
        try:
            with pytest.raises(
                LimitError,
                match=r"current_range applies to the RD6012P only, this"
                r" is an RD6006P \(model id 60065\); remove current_range",
            ):
                RidenSupply(link, name="coil_x", current_range=0)
        finally:
            link.close()


@pytest.mark.parametrize(("model_id", "current_range", "ovp_counts", "ocp_counts"), [
    (60062, 0, 1320, 1600),  # RD6006: 10 mV, 1 mA
    (60125, 0, 13200, 16000),  # RD6012P in its 6 A range: 1 mV, 0.1 mA
    (60125, 1, 13200, 1600),  # RD6012P in its 12 A range: 1 mV, 1 mA
])  # fmt: skip
def test_m0_ovp_and_ocp_set_and_read_back_in_the_models_counts(
    model_id: int, current_range: int, ovp_counts: int, ocp_counts: int
) -> None:
    with riden_image(model_id, r20=current_range) as image:
        supply = open_riden(image)
        try:
            levels = supply.set_protection_levels(ovp_v=13.2, ocp_a=1.6)
            assert (image.regs[82], image.regs[83]) == (ovp_counts, ocp_counts)
            assert [(p.kind, p.value, p.register) for p in levels] == [
                ("OVP", 13.2, "register 82 (M0 OVP)"), ("OCP", 1.6, "register 83 (M0 OCP)")]  # fmt: skip
            with pytest.raises(LimitError, match="has no over-power protection"):
                supply.set_protection_levels(opp_w=100.0)
        finally:
            supply.close()


def test_power_is_registers_12_and_13_as_one_32_bit_count() -> None:
    # An RD6030 on a real bench (riden-dongle issue #43) at 27.50 V, 28.03 A: a client reading
    # register 13 alone at 0.01 W showed 115.46 W; the true 770.8 W is 77082 counts, 1 * 65536 +
    # 11546: register 12 is the high word. The RD6012P counts 1 mW (its 13.5 W: 13500 counts).
    with riden_image(60301, r10=2750, r11=2803, r12=1, r13=11546) as image:
        supply = open_riden(image)
        try:
            assert supply.read().power_w == pytest.approx(770.82)
        finally:
            supply.close()
    with riden_image(60125, r12=0, r13=13500) as image:
        supply = open_riden(image)
        try:
            assert supply.read().power_w == pytest.approx(13.5)
        finally:
            supply.close()
