"""Shared synthetic-truth fixtures (generated here, seeded), the test tiers, and the check that
an installed-package run really tests the installed package."""

from __future__ import annotations

import importlib
import os
from pathlib import Path

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


TIERS = ("quick", "simcage", "realtime", "montecarlo", "services")
"""The test tiers (pyproject.toml's markers, docs/testing.md): a module names its tier in its
``pytestmark``; a test without one is quick."""
QUICK_TIMEOUT_S = 120.0
"""A quick test that has not finished in this long (s) is hung, not slow (they take seconds)."""


INSTALLED_ENV = "RIG_TEST_INSTALLED"
"""Set to 1 when the suite runs against a non-editable install (``.ci/run``'s second stage): the
product must then be imported from the install, never from the source tree beside the tests."""


def pytest_sessionstart(session: pytest.Session) -> None:
    """Refuse an installed-package run that would import the source tree instead."""
    if os.environ.get(INSTALLED_ENV) != "1":
        return
    checkout = Path(__file__).resolve().parents[1]
    for name in ("rig", "drivers", "sim", "regmaps", "timebase"):
        where = Path(importlib.import_module(name).__file__ or "").resolve()
        if where.is_relative_to(checkout):
            raise pytest.UsageError(f"{INSTALLED_ENV}=1 but {name} is imported from {where}: run"
                                    " 'python -P -m pytest --import-mode=append' from a venv with"
                                    " a non-editable install")  # fmt: skip


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test in exactly one tier; an unmarked one is quick, with the quick timeout."""
    for item in items:
        tiers = {m.name for m in item.iter_markers() if m.name in TIERS}
        if len(tiers) > 1:
            raise pytest.UsageError(f"{item.nodeid}: in tiers {sorted(tiers)}; give it one")
        if not tiers:
            item.add_marker(pytest.mark.quick)
            if item.get_closest_marker("timeout") is None:
                item.add_marker(pytest.mark.timeout(QUICK_TIMEOUT_S))


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
