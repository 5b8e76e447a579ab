"""Every shipped register map of a unipolar supply drives a coil and a load channel of the simulated
cage: the simulator serves the map (regmaps/) and the rig's drivers read the same file through the
same parser. Adding a supply as a register map adds it to this test by itself.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest

from regmaps import shipped_maps
from rig.config import load_rig_config
from rig.devices import build_cage, open_load
from sim.cage import SimulatedCage
from sim.config import load_config
from tests.sim.rig_toml import rig_toml

pytestmark = pytest.mark.realtime

SUPPLY_MAPS = sorted(m.name for m in shipped_maps() if m.kind == "supply" and not m.bipolar)


def supply_block(name: str, regmap: str, text: str) -> str:
    """The default cage's ``[[supplies]]`` entry ``name`` swapped for a register-map supply."""
    pattern = re.compile(r'\[\[supplies\]\]\nname = "' + name + r'"[^\[]*', re.S)
    block = pattern.search(text)
    assert block is not None, name
    lines = [ln for ln in block.group(0).splitlines() if not ln.startswith(("kind", "model_id"))]
    lines.insert(2, f'kind = "regmap"\nregmap = "{regmap}"')
    return text.replace(block.group(0), "\n".join(lines) + "\n")


@pytest.fixture(scope="module", params=SUPPLY_MAPS)
def sim_with_map(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[SimulatedCage, Path, str]]:
    regmap: str = request.param
    tmp = tmp_path_factory.mktemp(regmap)
    text = Path(load_config().source).read_text(encoding="utf-8")
    text = supply_block("load_bus", regmap, supply_block("coil_y", regmap, text))
    sim_path = tmp / "cage.toml"
    sim_path.write_text(text, encoding="utf-8")
    cfg = load_config(sim_path)
    with SimulatedCage(cfg) as cage:
        doc = cage.endpoints_document()
        for dev in doc["devices"].values():  # the rig reads the driver's copy, not the sim's
            if "regmap" in dev:
                dev["regmap"] = Path(dev["regmap"]).stem
        nominal = [list(r) for r in cfg.cage.coil_matrix_ut_per_a]
        rig_path = tmp / "rig.toml"
        rig_path.write_text(rig_toml(doc, nominal), encoding="utf-8")
        yield cage, rig_path, regmap


def test_the_map_drives_a_coil(sim_with_map: tuple[SimulatedCage, Path, str]) -> None:
    cage, rig_path, regmap = sim_with_map
    cfg = load_rig_config(rig_path)
    assert cfg.devices["coil_y"].kind == "regmap-supply"
    assert cfg.devices["coil_y"].get("regmap") == regmap
    with ExitStack() as stack:
        controller = build_cage(cfg, stack, cage.i2c_bus)
        controller.set_currents([0.0, 0.4, 0.0])
        time.sleep(0.3)
        np.testing.assert_allclose(cage.physics.coil_currents()[1], 0.4, atol=0.01)
        controller.set_currents([0.0, -0.3, 0.0])  # through zero, relay flipped at zero
        time.sleep(0.3)
        np.testing.assert_allclose(cage.physics.coil_currents()[1], -0.3, atol=0.01)
    assert not cage.physics.supplies["coil_y"].output


def test_the_map_drives_a_load_channel(sim_with_map: tuple[SimulatedCage, Path, str]) -> None:
    cage, rig_path, _ = sim_with_map
    load = open_load(load_rig_config(rig_path).devices["load_bus"])
    try:
        assert load.identify().model  # its model register reads what the map says
        assert cage.physics.supplies["load_bus"].output
        load.set_current(0.5)
        time.sleep(0.1)
        assert load.read().i_out_a == pytest.approx(0.5, abs=0.01)
    finally:
        load.safe()
        load.close()
    assert not cage.physics.supplies["load_bus"].output
