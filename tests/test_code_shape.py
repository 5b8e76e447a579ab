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
