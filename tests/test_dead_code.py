"""Dead code stays out (issue 57): vulture over the product, the tests and the benches finds
nothing but what ``dead_code_allowlist.py`` names with its reason."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("rig", "drivers", "sim", "regmaps", "timebase", "tests", "bench")


def test_no_code_that_nothing_reads() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "vulture", *SCANNED, "dead_code_allowlist.py",
         "--min-confidence", "60"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0 and not proc.stdout.strip(), (
        "dead code (remove it; if another program reads it, add it to dead_code_allowlist.py"
        f" with its reason):\n{proc.stdout}{proc.stderr}"
    )
