"""The test tiers are named and honest: every module's tier is one of pyproject's, and every
real-time module is named in docs/testing.md's real-time section with why it needs the wall clock."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

from tests.conftest import TIERS

ROOT = Path(__file__).resolve().parents[1]


def module_tiers() -> dict[Path, set[str]]:
    """Each test module's tiers from its ``pytestmark`` (``pytest.mark.<name>`` in it)."""
    found: dict[Path, set[str]] = {}
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        marks: set[str] = set()
        for node in tree.body:
            if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets
            ):
                marks |= {
                    a.attr
                    for a in ast.walk(node.value)
                    if isinstance(a, ast.Attribute)
                    and isinstance(a.value, ast.Attribute)
                    and a.value.attr == "mark"
                }
        found[path] = marks
    return found


def test_the_tiers_are_the_declared_markers_and_a_module_names_at_most_one() -> None:
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"][
        "ini_options"
    ]["markers"]
    assert sorted(m.split(":")[0] for m in declared) == sorted(TIERS)
    for path, marks in module_tiers().items():
        assert len(marks & set(TIERS)) <= 1, f"{path.relative_to(ROOT)}: tiers {sorted(marks)}"
        assert "slow" not in marks, f"{path.relative_to(ROOT)}: 'slow' is no tier; name one"


def test_every_real_time_module_is_named_in_the_real_time_section_of_docs_testing_md() -> None:
    text = (ROOT / "docs" / "testing.md").read_text(encoding="utf-8")
    section = text.split("## The real-time tier, and why", 1)[1].split("\n## ", 1)[0]
    realtime = [p for p, marks in module_tiers().items() if "realtime" in marks]
    assert len(realtime) > 40  # the wire, the guardian, the page, the signals
    unnamed = [
        str(p.relative_to(ROOT))
        for p in realtime
        if f"`{p.name}`" not in section
        and f"{p.relative_to(ROOT)}" not in section
        and f"`{p.parent.relative_to(ROOT)}/`" not in section
    ]
    assert not unnamed, f"real-time modules docs/testing.md does not name (say why): {unnamed}"
