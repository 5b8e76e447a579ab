"""Fixtures for the web page: a real `rig serve` process, Debian's chromium driven by Playwright.

Playwright drives the system browser (``/usr/bin/chromium``, or ``RIG_CHROMIUM``); nothing
downloads a browser build. Screenshots go to ``build/screenshots/`` in the repository.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from rig.child_process import start_child, stop_child
from tests.tools import require_tool

REPO = Path(__file__).resolve().parents[2]
SCREENSHOTS = REPO / "build" / "screenshots"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run",
                 "--disable-quic"]  # fmt: skip
"""The closed network refuses Chromium's own connections: switch them off."""


def chromium_path() -> str:
    """Debian's chromium (or ``RIG_CHROMIUM``); skips or fails without it (tests.tools)."""
    path = os.environ.get("RIG_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
    return require_tool("chromium", path, what="the page tests")


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS)
        yield b
        b.close()


def screenshot(page: Any, name: str) -> Path:
    """Save a full-page screenshot as ``build/screenshots/<name>.png``."""
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    path = SCREENSHOTS / f"{name}.png"
    page.screenshot(path=str(path), full_page=True)
    assert path.stat().st_size > 10_000, f"{path} is nearly empty"
    return path


def wait_js(page: Any, expression: str, timeout_s: float = 30.0) -> None:
    """Wait until the JavaScript ``expression`` is true in ``page``, polled from here: the page's
    Content-Security-Policy forbids the eval that Playwright's ``wait_for_function`` uses."""
    deadline = time.monotonic() + timeout_s
    while not page.evaluate(expression):
        assert time.monotonic() < deadline, f"not true within {timeout_s} s: {expression}"
        time.sleep(0.1)


def read_url(proc: subprocess.Popen[bytes], pattern: str, timeout_s: float = 60.0,
             stream: Any = None) -> str:  # fmt: skip
    """The first URL a child prints in a line matching ``pattern``, on ``stream`` (default: its
    stdout if piped, else its stderr)."""
    stream = stream or (proc.stdout if proc.stdout is not None else proc.stderr)
    assert stream is not None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = stream.readline().decode(errors="replace")
        if not line and proc.poll() is not None:
            break
        m = re.search(pattern + r"\s*(http://\S+)", line)
        if m:
            return m.group(1)
    raise AssertionError(f"no {pattern!r} line from {proc.args}")


def serve_process(runs_dir: Path, *extra: str) -> tuple[subprocess.Popen[bytes], str]:
    """`rig serve` on a free loopback port; returns the process and its address (with the access
    token: ``http://127.0.0.1:PORT/?token=...``)."""
    proc = start_child([sys.executable, "-m", "rig.cli", "serve", "--runs-dir", str(runs_dir),
                        "--port", "0", *extra], stdout=subprocess.PIPE)  # fmt: skip
    return proc, read_url(proc, "rig serve:")


def split_token(url: str) -> tuple[str, str]:
    """The printed address's base (``http://127.0.0.1:PORT``, no slash) and its access token."""
    base, token = url.split("?token=")
    return base.rstrip("/"), token


def owner_client(url: str) -> httpx.Client:
    """An HTTP client of the server's owner: it knows the token (as the owner's scripts do)."""
    base, token = split_token(url)
    return httpx.Client(base_url=base, headers={"authorization": f"Bearer {token}"}, timeout=30)


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[Path, str]]:
    runs = tmp_path / "runs"
    runs.mkdir()
    proc, url = serve_process(runs)
    try:
        yield runs, url
    finally:
        stop_child(proc, first=__import__("signal").SIGTERM, wait_s=5.0)
