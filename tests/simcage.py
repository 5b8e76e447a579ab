"""The simulated cage in this process with a rig configuration naming its endpoints: the setup
every test driving the rig on the simulator starts from (fixture ``sim_rig`` in tests/conftest.py,
or :func:`sim_cage` for a fixture of wider scope)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import NamedTuple

import timebase
from rig.sim_rig import sim_rig_config
from sim.cage import SimulatedCage
from sim.config import SimConfig, load_config


class SimRig(NamedTuple):
    """A started simulated cage and the rig configuration (TOML file) that opens it."""

    cage: SimulatedCage
    rig_toml: Path


def write_rig_toml(cage: SimulatedCage, folder: Path, cfg: SimConfig | None = None) -> Path:
    """``folder/rig.toml``: a rig configuration naming ``cage``'s endpoints (``cfg``: the cage's
    configuration, the default one if not given)."""
    path = folder / "rig.toml"
    path.write_text(sim_rig_config(cage.endpoints_document(), cfg or load_config()))
    return path


@contextmanager
def on_clock(simulated: bool, busy: timebase.BusyHost | None = None) -> Iterator[None]:
    """A fresh simulated clock joined by this thread (``simulated``; ``busy``: on a busy host),
    else the wall clock."""
    with ExitStack() as stack:
        if simulated:
            stack.enter_context(timebase.simulated(busy=busy))
        yield


@contextmanager
def sim_cage(
    folder: Path, cfg: SimConfig | None = None, *, simulated: bool = True,
    busy: timebase.BusyHost | None = None,
) -> Iterator[SimRig]:  # fmt: skip
    """A fresh simulated cage (``cfg``, else the default) and ``folder/rig.toml`` for it; the
    cage stops on leaving. ``simulated``: the cage, and everything this thread starts inside the
    block, on a fresh simulated clock (ADR 0038); False for the real-time tier. ``busy``: the
    simulated clock's host threads wake late, as on a busy computer (timebase.busy_host)."""
    cfg = cfg or load_config()
    with on_clock(simulated, busy), SimulatedCage(cfg) as cage:
        yield SimRig(cage, write_rig_toml(cage, folder, cfg))
