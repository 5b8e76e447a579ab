"""Shared synthetic-truth fixtures (generated here, seeded)."""

from __future__ import annotations

import pytest

from rig.calibration.synthetic import SyntheticCase, cage_like, rax_like


@pytest.fixture(scope="session")
def rax_case() -> SyntheticCase:
    """RAX-like on-orbit case: |h| 20-50 uT, 4 panel currents and EPS beacons, 0.1 uT noise."""
    return rax_like(3000, seed=11)


@pytest.fixture(scope="session")
def cage_case() -> SyntheticCase:
    """Cage sweep with a field vector, two load channels and a mounting rotation."""
    return cage_like(1500, seed=12)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--rig-config",
        default=None,
        help="a rig configuration (TOML) of real hardware: enables tests/hardware",
    )


@pytest.fixture(scope="session", autouse=True)
def private_lock_folder(tmp_path_factory: pytest.TempPathFactory) -> None:
    """The interlock's folder for this test session: private (0700, ours), so a /tmp/rig-locks
    left world-writable by an older version, or used by another session, does not matter here.
    Tests of the lock folder itself set their own."""
    import os

    folder = tmp_path_factory.mktemp("rig-locks")
    folder.chmod(0o700)
    os.environ["RIG_LOCK_DIR"] = str(folder)
