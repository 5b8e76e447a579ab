"""The code keeps the shape issue 32 gave it: no function over 60 lines outside argparse
declarations (``add_parser``: one option per line, long by nature), and no module of the engine
over 400 lines (the runner must not grow back into one object that does everything)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("rig", "drivers", "sim", "regmaps")
MAX_FUNCTION_LINES = 60
MAX_ENGINE_MODULE_LINES = 400
ARGPARSE_DECLARATIONS = {"add_parser"}


def test_no_function_is_over_60_lines() -> None:
    long = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    continue
                lines = (node.end_lineno or node.lineno) - node.lineno + 1
                if lines > MAX_FUNCTION_LINES and node.name not in ARGPARSE_DECLARATIONS:
                    long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({lines})")
    assert not long, "split these into named helpers: " + ", ".join(long)


def test_no_engine_module_is_over_400_lines() -> None:
    big = {p.name: n for p in (ROOT / "rig/engine").glob("*.py")
           if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_ENGINE_MODULE_LINES}  # fmt: skip
    assert not big, f"rig/engine modules over {MAX_ENGINE_MODULE_LINES} lines: {big}"


MIRROR_ROOMS = {"rig/cli", "rig/steps", "rig/web/lab_views", "sim"}
"""Rooms whose modules are named after what they mirror elsewhere: ``rig/cli/X`` is the command
``rig X``, ``rig/steps/X`` the step kind X, ``rig/web/lab_views/X`` the page /lab/X, ``sim/X`` the
simulated twin of a driver or a rig module."""


def test_a_module_name_repeats_only_where_its_room_says_what_it_is() -> None:
    """Issue 57: 'perming.py' three times, 'audit.py' and 'links.py' in rooms that did not say
    which was which. A name may repeat across the mirror rooms; once outside them at most (each
    package's own ``errors.py`` aside)."""
    rooms: dict[str, list[str]] = {}
    for package in (*PACKAGES, "timebase"):
        for path in (ROOT / package).rglob("*.py"):
            if path.name != "__init__.py" and "migrations" not in path.parts:
                rooms.setdefault(path.name, []).append(str(path.parent.relative_to(ROOT)))
    unclear = {
        name: sorted(where)
        for name, where in rooms.items()
        if len([r for r in where if r not in MIRROR_ROOMS]) > 1
        and not (name == "errors.py" and all("/" not in r for r in where))
    }
    assert not unclear, f"one name, rooms that do not say which is which: {unclear}"
