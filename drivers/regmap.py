"""Register-map data files: the drivers' name for the shared :mod:`regmaps` package (one folder of
maps and one validating parser for the drivers and the simulator, docs/adr/0019)."""

from __future__ import annotations

from regmaps import (
    MAP_DIR,
    ROLES,
    Register,
    RegisterMap,
    RegisterMapError,
    find_map,
    load_map,
    shipped_maps,
)

__all__ = [
    "MAP_DIR",
    "ROLES",
    "Register",
    "RegisterMap",
    "RegisterMapError",
    "find_map",
    "load_map",
    "shipped_maps",
]
