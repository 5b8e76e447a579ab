"""The cage controller with the real drivers against the simulated cage (pty, loopback TCP)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest

from rig.cage.characterize import characterize
from rig.cage.controller import CageController
from rig.cage.limits import CageLimitError
from rig.cage.model import CageModel
from rig.config import load_rig_config
from rig.devices import build_cage
from rig.sim_rig import rig_config_toml
from sim.cage import SimulatedCage
from sim.config import SimConfig, load_config
from sim.physics import springmann_matrix

pytestmark = pytest.mark.simcage


def fast_reference_config(tmp_path: Path) -> Path:
    """The default cage with the reference streaming at 100 Hz (shorter tests)."""
    text = Path(load_config().source).read_text()
    head, ref = text.split('name = "reference"')
    path = tmp_path / "cage.toml"
    path.write_text(head + 'name = "reference"' + ref.replace("rate_hz = 20", "rate_hz = 100", 1))
    return path


def certificate(cfg: SimConfig) -> str:
    """The reference's calibration certificate (its known small errors) as rig configuration."""
    ref = cfg.magnetometer("reference")
    lower = springmann_matrix(ref.scale, tuple(np.radians(ref.nonorth_deg)))
    matrix = np.linalg.inv(lower)
    rows = ", ".join("[" + ", ".join(f"{v:.12g}" for v in row) + "]" for row in matrix)
    offset = ", ".join(f"{v:.12g}" for v in ref.offset_ut)
    return f"correction_matrix = [{rows}]\ncorrection_offset_ut = [{offset}]\n"


@pytest.fixture(scope="module")
def sim_and_config(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[tuple[SimulatedCage, Path]]:
    tmp = tmp_path_factory.mktemp("cage")
    cfg = load_config(fast_reference_config(tmp))
    with SimulatedCage(cfg) as cage:
        text = rig_config_toml(
            cage.endpoints_document(), cfg.source, [list(r) for r in cfg.cage.coil_matrix_ut_per_a]
        )
        text = text.replace("[devices.reference]\n", "[devices.reference]\n" + certificate(cfg))
        rig_path = tmp / "rig.toml"
        rig_path.write_text(text)
        yield cage, rig_path


@pytest.fixture()
def controller(sim_and_config: tuple[SimulatedCage, Path]) -> Iterator[CageController]:
    cage, rig_path = sim_and_config
    with ExitStack() as stack:
        yield build_cage(load_rig_config(rig_path), stack, cage.i2c_bus)
    assert not any(s.output for s in cage.physics.supplies.values()), "outputs left on"


def test_characterization_recovers_k_and_b0(
    controller: CageController, sim_and_config: tuple[SimulatedCage, Path], tmp_path: Path
) -> None:
    cage, _ = sim_and_config
    model = characterize(controller, 1.0, samples=10, repeats=2, instruments={"reference": "sim"})
    physics = cage.physics
    mid = model.meta["mid_time_monotonic_s"]
    # what the reference sees: the coils' field per ampere where it sits, times the current per
    # reported ampere (the supplies' gains), and the lab field there at mid-sweep (ripple averaged)
    k_true = physics.coil_matrix_at["reference"] * physics.coil_gains(mid)
    where = cage.cfg.magnetometer("reference").position_m
    b0_true = np.mean(
        [physics.ambient_ut(t, False, where) for t in mid + np.linspace(-0.5, 0.5, 1001)], axis=0
    )
    z_k = (model.k_ut_per_a - k_true) / model.k_sigma
    z_b = (model.b0_ut - b0_true) / model.b0_sigma_ut
    # 12 K entries with 25-dof sigmas: the mean z^2 near 1 and no single entry far out
    assert np.mean(z_k**2) < 3.0 and np.abs(z_k).max() < 4.5, z_k
    assert np.abs(z_b).max() < 4.0, (model.b0_ut, b0_true, model.b0_sigma_ut)
    # idle, within 5 nT/A on 40 uT/A coils; this module keeps real transports (pty, TCP) on the
    # wall clock, and beside two CPU hogs and three other test workers one run's k_xx was 34 nT/A
    # off with its own sigma saying so (|z| < 4.5 above): the sigma is the promise judged, the
    # error only bounded (1.3e-3 of the constant)
    assert np.abs(model.k_ut_per_a - k_true).max() < 0.05
    assert model.meta["residual_rms_nt"] < 10.0
    # versioned file: a dated version plus the current pointer, and it reads back
    version = model.save(tmp_path / "cage.json")
    assert version.exists() and version != tmp_path / "cage.json"
    back = CageModel.load(tmp_path / "cage.json")
    np.testing.assert_allclose(back.k_ut_per_a, model.k_ut_per_a)
    assert back.meta["instruments"] == {"reference": "sim"}


def test_trim_reaches_10_nt_of_null_and_of_a_field(
    controller: CageController, sim_and_config: tuple[SimulatedCage, Path]
) -> None:
    cage, _ = sim_and_config
    # the trim judges by the reference's mean of 10 readings (5 nT each per axis): the field it
    # reached, where the reference sits, is within the tolerance plus what that mean cannot see
    # (3 sigma of its three-axis error, 8 nT); at the centre it had once read 10.25 nT beside two
    # CPU hogs, the reference being 8 cm away in the lab's and the coils' gradients
    sigma_mean_nt = 5.0 / np.sqrt(10) * np.sqrt(3)
    for target in (np.zeros(3), np.array([25.0, -15.0, 5.0])):
        result = controller.trim(target, tolerance_nt=10.0, settle_s=0.3)
        assert result.settled and result.error_nt <= 10.0, result
        now = time.monotonic()  # the true field there, with the 50 Hz ripple averaged out
        true = np.mean(
            [cage.physics.field_at_ut("reference", t, noise=False)
             for t in now - np.linspace(0, 0.2, 201)], axis=0,
        )  # fmt: skip
        true_err_nt = 1000 * np.linalg.norm(true - target)
        assert true_err_nt < 10.0 + 3 * sigma_mean_nt, true_err_nt


def test_polarity_flips_at_zero_and_limits_refuse(
    controller: CageController, sim_and_config: tuple[SimulatedCage, Path]
) -> None:
    cage, _ = sim_and_config
    hot = cage.physics.relays.hot_switches
    controller.set_currents([0.6, -0.4, 0.3])
    controller.set_currents([-0.5, 0.4, -0.3])
    time.sleep(0.2)
    np.testing.assert_allclose(cage.physics.coil_currents(), [-0.5, 0.4, -0.3], atol=2e-2)
    assert cage.physics.relays.hot_switches == hot
    sent = len(controller.sent)
    with pytest.raises(CageLimitError, match="field limit"):
        controller.set_field([100.0, 100.0, 0.0])
    with pytest.raises(CageLimitError, match=r"beyond the 2\.5 A limit"):
        controller.set_currents([0.0, 0.0, 3.0])
    assert len(controller.sent) == sent


def test_config_errors_name_file_and_key(tmp_path: Path) -> None:
    from rig.errors import UserInputError

    bad = tmp_path / "rig.toml"
    bad.write_text(
        '[devices.psu]\nkind = "riden-rd60xx"\nprotocol = "serial"\npath = "/dev/null"\n'
    )
    with pytest.raises(
        UserInputError, match=r"rig.toml: \[devices.psu\].protocol: 'serial' does not suit"
    ):
        load_rig_config(bad)
    bad.write_text('[devices.psu]\nkind = "riden-rd60xx"\nprotocol = "modbus-tcp"\nhost = "x"\n')
    with pytest.raises(UserInputError, match=r"needs 'port' for modbus-tcp"):
        load_rig_config(bad)
