"""A running simulated cage for the wire-level tests (one per module)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from sim.cage import SimulatedCage
from sim.config import load_config


@pytest.fixture(scope="module")
def cage() -> Iterator[SimulatedCage]:
    c = SimulatedCage(load_config())
    c.start()
    yield c
    c.stop()


@pytest.fixture(scope="module")
def devices(cage: SimulatedCage) -> dict[str, Any]:
    return cage.endpoints_document()["devices"]
