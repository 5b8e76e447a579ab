"""Register maps for the simulator: the shared :mod:`regmaps` parser (docs/adr/0019), with its
errors reported as configuration errors of the simulated cage."""

from __future__ import annotations

from regmaps import Register, RegisterMap, RegisterMapError, load_map
from sim.config import SimConfigError

__all__ = ["Register", "RegisterMap", "load_regmap"]


def load_regmap(path: str) -> RegisterMap:
    """Parse and check a register-map file (a path, or a shipped map's name)."""
    try:
        return load_map(path)
    except RegisterMapError as exc:
        raise SimConfigError(str(exc)) from None
