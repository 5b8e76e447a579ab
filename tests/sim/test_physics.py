"""Physics of the simulated cage against its own configuration (the truth)."""

from __future__ import annotations

import math
import re
import time
from pathlib import Path

import numpy as np
import pytest

from sim.config import SimConfigError, load_config
from sim.physics import CagePhysics, Magnetometer

T0 = 1000.0  # explicit times: the physics is evaluated at any given instant


@pytest.fixture()
def physics() -> CagePhysics:
    return CagePhysics(load_config(), start_s=0.0)


def drive(p: CagePhysics, currents_a: list[float], t_s: float) -> None:
    for axis, amps in enumerate(currents_a):
        supply = p.coil_supply[axis]
        supply.set_voltage(40.0, t_s)
        supply.set_current(abs(amps), t_s)
        if p.cfg.cage.polarity == "relay":
            p.set_polarity(axis, 1 if amps >= 0 else -1, t_s)
        supply.set_output(True, t_s)


def test_field_is_coil_matrix_times_current_plus_ambient(physics: CagePhysics) -> None:
    cfg = physics.cfg.cage
    currents = [0.8, -0.5, 1.2]
    drive(physics, currents, T0)
    tau = [cfg.inductance_h[i] / cfg.resistance_ohm[i] for i in range(3)]
    t_settled = T0 + 20 * max(tau)  # e^-20: settled to 1e-9
    # the supplies' gains written out from the configuration: error, drift, lab temperature
    lab_k = physics.lab.lab_temperature_c(t_settled - physics.start_s)
    gains = [1 + 1e-6 * (s.gain_ppm + s.gain_drift_ppm_per_h * t_settled / 3600
                         + s.gain_ppm_per_k * lab_k)
             for s in sorted((s for s in physics.cfg.supplies if s.axis is not None),
                             key=lambda s: s.axis)]  # fmt: skip
    expected = np.array(cfg.coil_matrix_ut_per_a) @ (np.array(currents) * gains)
    expected += physics.ambient_ut(t_settled, noise=False)
    np.testing.assert_allclose(physics.field_ut(t_settled, noise=False), expected, atol=1e-3)
    # one time constant into the step: 1 - 1/e of the way, per axis
    for axis in range(3):
        got = physics.coil_currents(T0 + tau[axis])[axis]
        assert math.isclose(got, currents[axis] * (1 - math.exp(-1)), rel_tol=1e-9)


def test_supply_cv_cc_and_protection(physics: CagePhysics) -> None:
    s = physics.supplies["coil_x"]
    r = s.resistance_ohm
    s.set_voltage(2.0, T0)
    s.set_current(5.0, T0)
    s.set_output(True, T0)
    assert not s.cc_mode() and math.isclose(s.output_current(T0 + 5), 2.0 / r)
    s.set_current(0.2, T0 + 5)
    assert s.cc_mode() and math.isclose(s.output_current(T0 + 10), 0.2)
    with pytest.raises(ValueError, match="outside"):
        s.set_voltage(70.0, T0 + 10)
    s.ocp_a = 0.1
    s.set_current(0.3, T0 + 11)  # above the OCP threshold
    assert s.protection == 2 and not s.output
    assert physics.supplies["coil_x"].output_current(T0 + 20) == pytest.approx(0.0, abs=1e-12)


def test_dut_reading_is_its_truth_model_within_noise(physics: CagePhysics) -> None:
    drive(physics, [0.5, 0.3, -0.4], T0)
    t = T0 + 1.0
    mag = physics.magnetometers["dut"]
    h = physics.field_ut(t, noise=False)
    readings = np.array([physics.read_magnetometer("dut", t) for _ in range(2000)])
    cfg = mag.cfg
    # truth written out independently: m = L R h + o (no load current flowing)
    a, b, c = cfg.scale
    rho, phi, lam = np.radians(cfg.nonorth_deg)
    lower = np.array([[a, 0, 0], [b * np.sin(rho), b * np.cos(rho), 0],
                      [c * np.sin(lam), c * np.sin(phi) * np.cos(lam), c * np.cos(phi) * np.cos(lam)]])  # fmt: skip
    rv = np.radians(cfg.mounting_deg)
    angle = np.linalg.norm(rv)
    k = rv / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rot = np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx
    truth = lower @ rot @ h + np.array(cfg.offset_ut)
    noise = cfg.noise_ut + physics.cfg.ambient.noise_ut
    assert np.all(np.abs(readings.mean(axis=0) - truth) < 5 * noise / np.sqrt(2000))
    np.testing.assert_allclose(readings.std(axis=0), cfg.noise_ut, rtol=0.1)


def test_load_current_biases_the_dut_after_its_delay(physics: CagePhysics) -> None:
    mag = physics.magnetometers["dut"]
    load = physics.supplies["load_panel"]
    load.set_voltage(12.0, T0)
    load.set_current(3.0, T0 + 1)
    load.set_output(True, T0 + 1)
    delay = mag.cfg.delay_s["load_panel"]
    k = np.array(mag.cfg.k_ut_per_a["load_panel"])
    t_before, t_after = T0 + 1 + 0.5 * delay, T0 + 1 + delay + 0.05
    assert physics.load_currents(t_before, mag.cfg.delay_s)["load_panel"] == pytest.approx(
        0.0, abs=1e-12
    )
    shift = mag.truth_reading(np.zeros(3), physics.load_currents(t_after, mag.cfg.delay_s))
    shift -= mag.truth_reading(np.zeros(3), {})
    np.testing.assert_allclose(shift, 3.0 * k, rtol=1e-6)


def test_stuck_sensor_repeats(physics: CagePhysics) -> None:
    mag: Magnetometer = physics.magnetometers["reference"]
    first = physics.read_magnetometer("reference", T0)
    mag.faults.stuck = True
    np.testing.assert_array_equal(physics.read_magnetometer("reference", T0 + 5), first)


def test_same_seed_same_cage() -> None:
    a, b = CagePhysics(load_config(), start_s=0.0), CagePhysics(load_config(), start_s=0.0)
    np.testing.assert_array_equal(a.read_magnetometer("dut", T0), b.read_magnetometer("dut", T0))
    later = CagePhysics(load_config(), start_s=500.0)  # the same lab field from its own start
    np.testing.assert_allclose(
        later.ambient_ut(T0 + 500.0, noise=False), a.ambient_ut(T0, noise=False), atol=1e-9
    )


def test_config_errors_name_the_key(tmp_path) -> None:  # type: ignore[no-untyped-def]
    text = load_config().source
    bad = tmp_path / "bad.toml"
    bad.write_text(Path(text).read_text().replace('polarity = "relay"', 'polarity = "sideways"'))
    with pytest.raises(SimConfigError, match=r"cage.polarity must be 'relay' or 'bipolar'"):
        load_config(bad)
    bad.write_text("[cage\n")
    with pytest.raises(SimConfigError, match="not valid TOML"):
        load_config(bad)


def bipolar_config(tmp_path: Path) -> Path:
    text = Path(load_config().source).read_text()
    text = text.replace('polarity = "relay"', 'polarity = "bipolar"')
    for axis in "xyz":
        text = re.sub(
            rf'kind = "riden-rd60xx"\nmodel_id = \d+[^\n]*\naxis = "{axis}"',
            f'kind = "regmap"\nregmap = "bipolar-supply"\naxis = "{axis}"',
            text,
        )
    path = tmp_path / "bipolar.toml"
    path.write_text(text)
    return path


def test_bipolar_supply_reverses_through_zero_over_modbus(tmp_path: Path) -> None:
    from pymodbus.client import ModbusTcpClient

    from sim.cage import SimulatedCage

    cfg = load_config(bipolar_config(tmp_path))
    assert cfg.cage.polarity == "bipolar"
    with SimulatedCage(cfg) as cage:
        dev = cage.endpoints_document()["devices"]["coil_x"]
        assert dev["kind"] == "regmap-supply"
        with ModbusTcpClient("127.0.0.1", port=dev["port"], timeout=2) as c:
            assert not c.write_register(0x10, 1000, device_id=1).isError()  # 10 V
            assert not c.write_register(0x11, 400, device_id=1).isError()  # +0.4 A
            assert not c.write_register(0x12, 1, device_id=1).isError()
            time.sleep(0.3)
            assert abs(cage.physics.coil_currents()[0] - 0.4) < 1e-3
            neg = (-400) & 0xFFFF  # int16 two's complement
            t_asked = time.monotonic()
            assert not c.write_register(0x11, neg, device_id=1).isError()
            t_answered = time.monotonic()  # the flip happened in between, however long that took
            tau = cfg.cage.inductance_h[0] / cfg.cage.resistance_ohm[0]
            # continuously through zero: an L/R decay from +0.4 A toward -0.4 A, i(t) = -0.4 +
            # 0.8 exp(-(t - t_flip) / tau), which crosses zero tau ln 2 after the flip; every
            # sample after the answer must put the flip between the request and the answer
            t = np.linspace(t_answered, t_answered + 3 * tau, 500)
            i = np.array([cage.physics.coil_currents(tk)[0] for tk in t])
            implied_flip = t + tau * np.log((i + 0.4) / 0.8)
            assert np.all(implied_flip >= t_asked - 1e-3), (implied_flip - t_asked).min()
            assert np.all(implied_flip <= t_answered + 1e-3), (implied_flip - t_answered).max()
            assert np.all(np.diff(i) < 0)  # no jump back: a monotonic decay through zero
            assert i[-1] < 0
            time.sleep(0.3)
            i_out = c.read_holding_registers(0x21, count=1, device_id=1).registers[0]
            assert i_out == neg  # signed readback
            assert abs(cage.physics.coil_currents()[0] + 0.4) < 1e-3


def test_faults_from_the_configuration(tmp_path: Path) -> None:
    from sim.cage import SimulatedCage

    path = tmp_path / "faulty.toml"
    path.write_text(Path(load_config().source).read_text() + "\n[faults.dut]\nstuck = true\n")
    with SimulatedCage(load_config(path)) as cage:
        assert cage.faults["dut"].stuck is True
    path.write_text(Path(load_config().source).read_text() + "\n[faults.nobody]\nsilent = true\n")
    with pytest.raises(SimConfigError, match=r"faults\.nobody: no device"):
        load_config(path)


def test_the_heater_warms_the_dut_as_a_first_order_thermal_mass(physics: CagePhysics) -> None:
    """tau dT/dt = ambient + k I^2 R - T: after one time constant 63 % of the way, and the DUT's
    reading moves by its temperature coefficients (scale and offset per kelvin) exactly."""
    thermal = physics.cfg.thermal
    assert thermal is not None
    heater = physics.supplies[thermal.heater]
    assert physics.dut_temperature_c(T0) == pytest.approx(thermal.ambient_c)
    heater.set_voltage(12.0, T0)
    heater.set_current(2.0, T0)
    heater.set_output(True, T0)
    rise_k = thermal.k_per_w * 2.0**2 * heater.resistance_ohm
    t_one = T0 + thermal.tau_s
    assert physics.dut_temperature_c(t_one) - thermal.ambient_c == pytest.approx(
        rise_k * (1 - math.exp(-1)), rel=1e-9
    )
    heater.set_output(False, t_one)  # cools from where it got to
    assert physics.dut_temperature_c(t_one + thermal.tau_s) - thermal.ambient_c == pytest.approx(
        rise_k * (1 - math.exp(-1)) * math.exp(-1), rel=1e-9
    )
    mag = physics.magnetometers["dut"]
    h = np.array([30.0, -10.0, 20.0])
    d_t = 12.0
    warm = mag.truth_reading(h, {}, mag.cfg.temperature_ref_c + d_t)
    expected = (1 + mag.cfg.scale_per_k * d_t) * (mag.t_matrix @ h) + mag.offset_ut
    expected += np.array(mag.cfg.offset_ut_per_k) * d_t
    np.testing.assert_allclose(warm, expected, rtol=1e-12)
    assert mag.cfg.scale_per_k != 0 and np.any(mag.offset_ut_per_k != 0)


def test_a_heater_that_is_no_load_channel_is_refused(tmp_path: Path) -> None:
    text = Path(load_config().source).read_text().replace('heater = "heater"', 'heater = "coil_x"')
    path = tmp_path / "cage.toml"
    path.write_text(text)
    with pytest.raises(SimConfigError, match="no load channel"):
        load_config(path)
