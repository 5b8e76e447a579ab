"""`rig sim` as a child process for tests that drive the rig across process boundaries."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


@contextmanager
def sim_process(folder: Path) -> Iterator[tuple[Path, dict[str, Any]]]:
    """Start `rig sim`, yield (rig configuration path, devices of the endpoints file), stop it."""
    rig_toml, ep = folder / "rig.toml", folder / "endpoints.json"
    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", "-q", "sim", "--rig-config", str(rig_toml),
                             "--endpoints-json", str(ep)])  # fmt: skip
    try:
        deadline = time.monotonic() + 20
        while not (rig_toml.exists() and ep.exists()):
            assert proc.poll() is None and time.monotonic() < deadline, "rig sim did not start"
            time.sleep(0.05)
        yield rig_toml, json.loads(ep.read_text())["devices"]
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=15)
