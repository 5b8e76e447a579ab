"""Fixtures shared by engine tests that drive the simulated cage in this process."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from sim.cage import SimulatedCage
from sim.config import load_config
from tests.simcage import write_rig_toml


@pytest.fixture(scope="module")
def cage() -> Iterator[SimulatedCage]:
    """The default simulated cage, one per test module (a module's own ``cage`` wins)."""
    with SimulatedCage(load_config()) as sim:
        yield sim


@pytest.fixture
def rig_toml(cage: SimulatedCage, tmp_path: Path) -> Path:
    """A rig configuration naming the cage's endpoints."""
    return write_rig_toml(cage, tmp_path)


@pytest.fixture
def own_lock_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A lock folder of this test's own (``pytestmark = pytest.mark.usefixtures(...)``)."""
    monkeypatch.setenv("RIG_LOCK_DIR", str(tmp_path / "locks"))
