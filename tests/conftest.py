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


LONGEST_FIRST = (
    "tests/engine/test_runs_e2e.py",
    "tests/web/test_page_in_browser.py",
    "tests/test_uncertainty_audit.py",
    "tests/engine/test_fault_matrix.py",
    "tests/test_cli_newcomer.py",
    "tests/engine/test_frequency_response_on_sim.py",
    "tests/engine/test_sines_on_a_busy_host.py",
    "tests/lab/test_lab_index.py",
)
"""The files that take longest (``--durations`` on an idle run, 2026-11-29: 40-145 s each), run
first: with ``--dist loadfile`` a file runs whole on one worker, and one of these started last
kept the suite waiting a minute and a half for it alone (an idle clean-clone run: 620 s)."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The longest files first (:data:`LONGEST_FIRST`), every other test in collection order."""
    rank = {path: i for i, path in enumerate(LONGEST_FIRST)}

    def key(item: pytest.Item) -> int:
        return rank.get(item.nodeid.split("::", 1)[0], len(rank))

    items.sort(key=key)  # stable: the order within a file and among the rest is kept
