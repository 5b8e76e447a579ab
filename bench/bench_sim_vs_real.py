"""The same acceptance in simulated and in real time (ADR 0038): for each seed, `rig demo` beside
`rig sim` (real time) and `rig demo --simulated-time`, the same simulator configuration; prints
both verdicts and, per fitted parameter of the vector calibration (Springmann's nine), how far
apart the two are in their combined sigmas (|a - b| / sqrt(sa^2 + sb^2)): the two clocks measure
the same cage when the verdicts agree and the distances look like draws of |N(0, 1)|.

Run: ``.venv/bin/python bench/bench_sim_vs_real.py [--seeds 7 8 9]`` (about 3 minutes a seed).
"""

from __future__ import annotations

import argparse
import math
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def run(folder: Path, sim_toml: Path, simulated: bool) -> tuple[dict[str, Any], float]:
    """One demo; (the vector calibration's result, wall seconds)."""
    from rig.store import RunReader

    argv = [sys.executable, "-m", "rig.cli", "-q", "demo", "--runs-dir", str(folder),
            "--sim-config", str(sim_toml)] + (["--simulated-time"] if simulated else [])  # fmt: skip
    t0 = time.monotonic()
    subprocess.run(argv, check=False, capture_output=True, text=True, timeout=900)
    took = time.monotonic() - t0
    (run_dir,) = [p for p in folder.iterdir() if (p / "run.sqlite").exists()]
    reader = RunReader(run_dir)
    results = reader.results()
    reader.close()
    return results, took


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[7, 8, 9], help="simulator seeds")
    args = parser.parse_args()
    template = (ROOT / "sim" / "default_cage.toml").read_text(encoding="utf-8")
    distances: list[float] = []
    for seed in args.seeds:
        with tempfile.TemporaryDirectory(prefix="simvsreal-") as tmp:
            sim_toml = Path(tmp) / "cage.toml"
            sim_toml.write_text(re.sub(r"(?m)^seed = \d+", f"seed = {seed}", template))
            real, real_s = run(Path(tmp) / "real", sim_toml, simulated=False)
            simu, simu_s = run(Path(tmp) / "sim", sim_toml, simulated=True)
        a, b = real["vector calibration"], simu["vector calibration"]
        gaps = {k: abs(a["springmann"][k] - b["springmann"][k])
                / math.hypot(a["combined_sigma"]["springmann"][k], b["combined_sigma"]["springmann"][k])
                for k in a["springmann"]}  # fmt: skip
        distances += gaps.values()
        print(f"seed {seed}: verdict real {real['verdict']['overall']} ({real_s:.0f} s),"
              f" simulated {simu['verdict']['overall']} ({simu_s:.0f} s); largest gap"
              f" {max(gaps.values()):.2f} sigma ({max(gaps, key=gaps.__getitem__)})")  # fmt: skip
    rms = math.sqrt(sum(d * d for d in distances) / len(distances))
    within = sum(d <= 1.0 for d in distances) / len(distances)
    print(
        f"{len(distances)} parameters: rms gap {rms:.2f} sigma, {100 * within:.0f} % within"
        " 1 sigma (|N(0,1)|: 1.00 and 68 %)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
