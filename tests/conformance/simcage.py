"""A simulated cage with chosen supplies swapped in, for the conformance tests."""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sim.cage import SimulatedCage
from sim.config import load_config


def swap_supply(text: str, name: str, lines: str) -> str:
    """The default cage's ``[[supplies]]`` entry ``name`` with its kind/model lines replaced."""
    pattern = re.compile(r'\[\[supplies\]\]\nname = "' + name + r'"[^\[]*', re.S)
    block = pattern.search(text)
    assert block is not None, name
    kept = [ln for ln in block.group(0).splitlines()
            if not ln.startswith(("kind", "model_id", "regmap", "baudrate"))]  # fmt: skip
    kept.insert(2, lines)
    return text.replace(block.group(0), "\n".join(kept) + "\n")


@contextmanager
def cage_with(tmp: Path, swaps: dict[str, str]) -> Iterator[SimulatedCage]:
    """The default cage with ``swaps`` (supply name -> its new kind/model lines), started."""
    text = Path(load_config().source).read_text(encoding="utf-8")
    for name, lines in swaps.items():
        text = swap_supply(text, name, lines)
    path = tmp / "cage.toml"
    path.write_text(text, encoding="utf-8")
    with SimulatedCage(load_config(path)) as cage:
        yield cage


def endpoint(cage: SimulatedCage, name: str) -> dict[str, Any]:
    """The endpoints document's entry of device ``name``."""
    return dict(cage.endpoints_document()["devices"][name])
