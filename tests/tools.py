"""External tools some tests need (Debian packages ``.ci/run`` installs): a test skips without
its tool, unless ``RIG_REQUIRE_TOOLS`` is set (``.ci/run`` sets it), where a missing tool fails
the test instead, so CI never passes by skipping.

Every test needing such a tool asks for it through :func:`require_tool`.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

REQUIRE_TOOLS = "RIG_REQUIRE_TOOLS"
OLD_VARIABLES = {"chromium": "RIG_REQUIRE_BROWSER", "postgresql": "RIG_REQUIRE_POSTGRES"}
"""Older variables that require one tool each (still honoured)."""
PACKAGES = {"mbpoll": "mbpoll", "pdftoppm": "poppler-utils", "pdftotext": "poppler-utils", "chromium": "chromium",
            "postgresql": "postgresql"}  # fmt: skip
"""The Debian package of each tool (what ``.ci/run`` installs)."""


def _set(variable: str) -> bool:
    return os.environ.get(variable, "").strip() not in ("", "0")


def tools_required(tool: str) -> bool:
    """True when a missing ``tool`` must fail the test rather than skip it."""
    old = OLD_VARIABLES.get(tool)
    return _set(REQUIRE_TOOLS) or (old is not None and _set(old))


def require_tool(tool: str, found: str | Path | None = None, *, what: str = "") -> str:
    """The tool's path: ``found`` if given (a path that must exist), else ``tool`` on PATH.
    Without it the test skips, or fails when :func:`tools_required`; ``what`` names the tests."""
    path = str(found) if found is not None else shutil.which(tool)
    if path is not None and Path(path).exists():
        return path
    package = PACKAGES.get(tool, tool)
    why = f"{tool} is needed{f' for {what}' if what else ''}: apt-get install {package}"
    if tools_required(tool):
        pytest.fail(f"{why} ({REQUIRE_TOOLS} is set: a missing tool fails, never skips)")
    pytest.skip(f"{why} (.ci/run installs it)")
