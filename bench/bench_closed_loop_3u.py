"""A 3U CubeSat detumbled by B-dot in closed loop on the simulated cage, in simulated time (issue
56's must-show; the tests use a spacecraft 30 times lighter in a field turning 30 times faster,
to detumble in a minute): the shipped closed-loop procedure with the step's defaults for the
spacecraft (principal moments 0.0333, 0.0333, 0.0067 kg m^2; rods of 0.2 A m^2), tumbling at
10 deg/s in the orbit's own field (time_scale 1), until below ``--until`` deg/s.

Prints the detumble through the cage and all in software (the same scenario, the DUT's measured
noise), their difference, and the wall time against the simulated time (the baseline: real time,
ratio 1).

Usage: ``.venv/bin/python bench/bench_closed_loop_3u.py [--until 2] [--rate-hz 5]``
(needs the ``[hil]`` extra: Basilisk)
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
from pathlib import Path

from rig.cli import main as rig_main
from rig.procedure_files import find_procedure
from rig.store import RunReader


def shipped_loop(values: dict[str, float], drop: tuple[str, ...] = ()) -> str:
    """The shipped closed-loop procedure with its loop's ``values`` set, the keys in ``drop``
    left out (the step's defaults) and no check step (the benches report figures, not a verdict)."""
    text = find_procedure("closed-loop-detumble").read_text()
    for key in drop:
        text = re.sub(rf"\n +{key}: .*", "", text)
    for key, value in values.items():
        text = re.sub(rf"\b{key}: \S+", f"{key}: {value:g}", text)
    return re.sub(r"  - check:\n(.*\n)*?  - report", "  - report", text)


def procedure(until_deg_s: float, rate_hz: float, duration_s: float) -> str:
    """The shipped closed-loop procedure with a 3U CubeSat (the step's default inertia and rods)
    in the orbit's own field."""
    return shipped_loop({"time_scale": 1, "rate_hz": rate_hz, "duration_s": duration_s,
                         "until_deg_s": until_deg_s}, drop=("inertia_kg_m2", "max_dipole_am2"))  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--until", type=float, default=2.0, help="detumbled below (deg/s)")
    parser.add_argument("--rate-hz", type=float, default=5.0, help="loop ticks per second")
    parser.add_argument("--duration-s", type=float, default=14400.0, help="longest loop (s)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cubesat.yaml"
        path.write_text(procedure(args.until, args.rate_hz, args.duration_s))
        runs = Path(tmp) / "runs"
        started = time.perf_counter()
        code = rig_main(["-q", "demo", "--procedure", str(path), "--simulated-time",
                         "--runs-dir", str(runs)])  # fmt: skip
        wall = time.perf_counter() - started
        folder = next(p for p in runs.iterdir() if (p / "run.sqlite").exists())
        reader = RunReader(folder)
        try:
            result = reader.results()["detumble"]
            steps = reader.steps()
        finally:
            reader.close()
    simulated = sum((end or start) - start for _, _, _, start, end in steps)
    print(f"3U CubeSat at 10 deg/s, B-dot through the simulated cage: {result['summary']}")
    print(f"run exit code {code}; {simulated:.0f} s of simulated time took {wall:.0f} s of wall"
          f" time ({simulated / wall:.1f}x real time, baseline 1.0)")  # fmt: skip
    return 0 if result["detumble_s"] is not None else 1


if __name__ == "__main__":
    sys.exit(main())
