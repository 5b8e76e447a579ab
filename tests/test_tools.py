"""A test whose tool is missing skips, and fails instead under RIG_REQUIRE_TOOLS (CI)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from tests.tools import OLD_VARIABLES, REQUIRE_TOOLS, require_tool

NO_TOOL = "rig-no-such-tool"


@pytest.fixture(autouse=True)
def _no_requirement(monkeypatch: pytest.MonkeyPatch) -> None:
    for variable in (REQUIRE_TOOLS, *OLD_VARIABLES.values()):
        monkeypatch.delenv(variable, raising=False)


def test_a_tool_found_is_its_path() -> None:
    assert require_tool("python", sys.executable) == sys.executable
    assert Path(require_tool("sh")).name == "sh"


def test_a_missing_tool_skips_saying_what_to_install() -> None:
    with pytest.raises(pytest.skip.Exception, match="apt-get install poppler-utils"):
        require_tool("pdftoppm", "/nonexistent/pdftoppm")


@pytest.mark.parametrize("value", ["1", "yes"])
def test_a_missing_tool_fails_when_tools_are_required(
    monkeypatch: pytest.MonkeyPatch, value: str
) -> None:
    monkeypatch.setenv(REQUIRE_TOOLS, value)
    with pytest.raises(pytest.fail.Exception, match=f"{NO_TOOL} is needed.*{REQUIRE_TOOLS}"):
        require_tool(NO_TOOL)


def test_zero_or_empty_requires_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    for value in ("0", ""):
        monkeypatch.setenv(REQUIRE_TOOLS, value)
        with pytest.raises(pytest.skip.Exception):
            require_tool(NO_TOOL)


def test_the_older_variables_require_their_own_tool_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RIG_REQUIRE_BROWSER", "1")
    with pytest.raises(pytest.fail.Exception):
        require_tool("chromium", "/nonexistent/chromium")
    with pytest.raises(pytest.skip.Exception):
        require_tool("postgresql", None)
    monkeypatch.setenv("RIG_REQUIRE_POSTGRES", "1")
    with pytest.raises(pytest.fail.Exception):
        require_tool("postgresql", None)


def test_ci_requires_every_tool_and_no_test_skips_for_one_on_its_own() -> None:
    root = Path(__file__).resolve().parents[1]
    assert re.search(rf"^export {REQUIRE_TOOLS}=1", (root / ".ci/run").read_text(), re.M)
    tests = [
        p for p in (root / "tests").rglob("*.py") if p.name not in ("tools.py", "test_tools.py")
    ]
    for path in tests:
        text = path.read_text()
        for old in OLD_VARIABLES.values():
            assert old not in text, f"{path} reads {old}: use tests.tools.require_tool"
        for tool in ("mbpoll", "pdftoppm", "chromium", "postgres"):
            own = re.search(rf"(pytest\.skip\(|skipif\()[^)]*{tool}", text, re.I)
            assert not own, f"{path}: skips for {tool} on its own: use tests.tools.require_tool"
