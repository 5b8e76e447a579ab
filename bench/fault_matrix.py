"""Run the whole fault matrix on the simulated cage and regenerate docs/reliability.md.

    .venv/bin/python bench/fault_matrix.py [--out docs/reliability.md]

Each fault is injected 1.5 s into a sphere sweep with two load channels (see bench/faultlab.py);
the figures are this machine's. The soak figure comes from bench/soak.py and is kept from the
previous document unless --soak gives a new line.
"""

from __future__ import annotations

import argparse
import datetime as dt
import platform
import tempfile
import time
from pathlib import Path

from faultlab import FAULTS, markdown, run_fault

from rig import __version__

DOC = Path(__file__).resolve().parents[1] / "docs" / "reliability.md"
SOAK_MARK = "<!-- soak -->"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DOC)
    ap.add_argument("--soak", help="the soak result line to record (from bench/soak.py)")
    args = ap.parse_args()
    rows = []
    t0 = time.monotonic()
    for fault in FAULTS:
        m = run_fault(fault, Path(tempfile.mkdtemp(prefix=f"fault-{fault.key}-")))
        safe = "-" if m.time_to_safe_ms is None else f"{m.time_to_safe_ms:.0f} ms"
        print(
            f"{fault.key:17s} {m.status:10s} exit {m.exit_code:4d}  safe {safe:>8s}  "
            f"{'as expected' if m.ok else 'NOT AS EXPECTED: ' + '; '.join(m.problems)}",
            flush=True,
        )
        rows.append(m)
    soak = args.soak
    if soak is None and args.out.exists():
        old = args.out.read_text(encoding="utf-8")
        if SOAK_MARK in old:
            soak = old.split(SOAK_MARK)[1].strip()
    template = (Path(__file__).with_name("reliability_template.md")).read_text(encoding="utf-8")
    text = template.format(
        matrix=markdown(rows),
        when=dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        machine=f"{platform.machine()}, Python {platform.python_version()}, rig {__version__}",
        took=f"{time.monotonic() - t0:.0f}",
        soak=f"{SOAK_MARK}\n{soak or 'not measured yet: run bench/soak.py'}\n{SOAK_MARK}",
    )
    args.out.write_text(text, encoding="utf-8")
    print(f"wrote {args.out}: {sum(m.ok for m in rows)}/{len(rows)} faults as expected")
    return 0 if all(m.ok for m in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
