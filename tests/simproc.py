"""`rig sim` as a child process for tests that drive the rig across process boundaries."""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from rig.child_process import start_child, stop_child


@contextmanager
def sim_process(
    folder: Path, argv: Sequence[str] | None = None, stop_wait_s: float = 15.0
) -> Iterator[tuple[Path, dict[str, Any]]]:
    """Start `rig sim`, yield (rig configuration path, devices of the endpoints file), stop it.

    The child dies with this process (SIGTERM from the kernel on Linux, see rig.child_process)
    even when pytest itself is killed; on the normal path it gets SIGINT, ``stop_wait_s`` (s) to
    stop, then SIGKILL. ``argv`` replaces the command (tests of this helper); it must write both
    files, whose paths are appended as ``--rig-config RIG --endpoints-json EP``.
    """
    rig_toml, ep = folder / "rig.toml", folder / "endpoints.json"
    command = list(argv) if argv is not None else [sys.executable, "-m", "rig.cli", "-q", "sim"]
    proc = start_child([*command, "--rig-config", str(rig_toml), "--endpoints-json", str(ep)])
    try:
        deadline = time.monotonic() + 20
        while not (rig_toml.exists() and ep.exists()):
            assert proc.poll() is None and time.monotonic() < deadline, "rig sim did not start"
            time.sleep(0.05)
        yield rig_toml, json.loads(ep.read_text())["devices"]
    finally:
        stop_child(proc, wait_s=stop_wait_s)
