"""Run the fault matrix on the simulated cage and regenerate docs/reliability.md.

    .venv/bin/python bench/fault_matrix.py [--quick] [--out docs/reliability.md]

Every fault of bench/faultlab.py is injected 1.5 s into every step kind that drives outputs
(``--quick``: the diagonal CI runs, each fault and each kind once), then the interlock and cage
command cells; the figures are this machine's. The soak figure comes from bench/soak.py and is
kept from the previous document unless --soak gives a new line.
"""

from __future__ import annotations

import argparse
import datetime as dt
import platform
import tempfile
import time
from pathlib import Path

from faultlab import EXTRA, Measured, cells, markdown, run_extra, run_fault

from rig import __version__

DOC = Path(__file__).resolve().parents[1] / "docs" / "reliability.md"
SOAK_MARK = "<!-- soak -->"
ATTACK_MARK = "<!-- attacks -->"  # bench/attack_matrix.py's section, kept as it is


def _line(m: Measured) -> str:
    safe = "-" if m.time_to_safe_ms is None else f"{m.time_to_safe_ms:.0f} ms"
    verdict = "as expected" if m.ok else "NOT AS EXPECTED: " + "; ".join(m.problems)
    return f"{m.fault.key:17s} {m.kind:18s} {m.status:10s} exit {m.exit_code:4d}  safe {safe:>8s}  {verdict}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=DOC, help="document to write (default: %(default)s)"
    )
    ap.add_argument("--quick", action="store_true", help="the diagonal only (as CI runs it)")
    ap.add_argument("--soak", help="the soak result line to record (from bench/soak.py)")
    args = ap.parse_args()
    rows = []
    t0 = time.monotonic()
    for fault, kind in cells(full=not args.quick):
        m = run_fault(fault, Path(tempfile.mkdtemp(prefix=f"fault-{fault.key}-{kind}-")), kind)
        print(_line(m), flush=True)
        rows.append(m)
    for fault in EXTRA:
        m = run_extra(fault, Path(tempfile.mkdtemp(prefix=f"fault-{fault.key}-")))
        print(_line(m), flush=True)
        rows.append(m)
    soak = args.soak
    if soak is None and args.out.exists():
        old = args.out.read_text(encoding="utf-8")
        if SOAK_MARK in old:
            soak = old.split(SOAK_MARK)[1].strip()
    attacks = "not measured yet: run bench/attack_matrix.py"
    if args.out.exists() and ATTACK_MARK in (old := args.out.read_text(encoding="utf-8")):
        attacks = old.split(ATTACK_MARK)[1].strip()
    template = (Path(__file__).with_name("reliability_template.md")).read_text(encoding="utf-8")
    text = template.format(
        matrix=markdown(rows),
        when=dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        machine=f"{platform.machine()}, Python {platform.python_version()}, rig {__version__}",
        took=f"{time.monotonic() - t0:.0f}",
        cells=len(rows),
        soak=f"{SOAK_MARK}\n{soak or 'not measured yet: run bench/soak.py'}\n{SOAK_MARK}",
        attacks=f"{ATTACK_MARK}\n{attacks}\n{ATTACK_MARK}",
    )
    args.out.write_text(text, encoding="utf-8")
    print(f"wrote {args.out}: {sum(m.ok for m in rows)}/{len(rows)} cells as expected")
    return 0 if all(m.ok for m in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
