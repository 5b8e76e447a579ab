"""Orbit replay timing: field commands at 50 Hz for 5 simulated minutes, and `rig demo` wall time.

Starts `rig sim` as a child process, replays an ISS orbit (nadir pointing, real time) through the
cage controller at 50 Hz while the DUT and the reference stream, and prints:
  * lateness of field commands (start versus schedule): p50, p99, max, and p99 as a fraction of
    the 20 ms command period measured in the same run (target: p99 <= 2 ms);
  * magnetometer samples: recorded versus expected from the sensor rate, and gaps longer than
    1.5 sample periods (target: none lost);
  * the whole `rig demo` as a subprocess (target: under 2 minutes).

Usage: python bench/bench_orbit_replay.py [--seconds 300] [--skip-demo]
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from rig.config import load_rig_config
from rig.engine.runner import Runner
from rig.procedure.language import parse_procedure
from rig.store import RunReader

PROCEDURE = """
procedure: orbit timing benchmark
magnetometers: {{dut: dut, reference: reference}}
steps:
  - orbit_replay:
      tle:
        - "1 25544U 98067A   19343.69339541  .00001764  00000-0  38792-4 0  9991"
        - "2 25544  51.6439 211.2001 0007417  17.6667  85.6398 15.50103472202482"
      start: "2019-12-09T12:00:00Z"
      duration_s: {seconds}
      time_scale: 1
      rate_hz: 50
      attitude: nadir
"""


@contextlib.contextmanager
def simulated_cage(folder: Path) -> Iterator[Path]:
    """`rig sim` as a child process writing its rig configuration into ``folder``; yields the
    configuration's path, stops the simulator (Ctrl-C) at the end."""
    rig_toml = folder / "rig.toml"
    child = subprocess.Popen(
        [sys.executable, "-m", "rig.cli", "-q", "sim", "--rig-config", str(rig_toml)]
    )
    try:
        while not rig_toml.exists():
            assert child.poll() is None, "rig sim did not start"
            time.sleep(0.05)
        yield rig_toml
    finally:
        child.send_signal(signal.SIGINT)
        child.wait(timeout=15)


def sample_gaps(
    reader: RunReader, whole_run: bool = False
) -> dict[str, tuple[int, float, float, int]]:
    """Per magnetometer during the first step (or from its first to its last sample): (samples,
    expected from the median rate, rate Hz, gaps longer than 1.5 sample periods)."""
    out = {}
    steps = reader.steps()
    for dev in reader.devices():
        t = np.array([row[0] for row in reader.samples(dev)])
        if t.size < 3:
            out[dev] = (int(t.size), 0.0, 0.0, 0)
            continue
        rate = 1.0 / np.median(np.diff(t))
        t0, t1 = (t[0], t[-1]) if whole_run else (steps[0][3], steps[0][4] or t[-1])
        inside = t[(t >= t0) & (t <= t1)]
        gaps = int(np.sum(np.diff(inside) > 1.5 / rate))
        out[dev] = (int(inside.size), (t1 - t0) * rate, float(rate), gaps)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--skip-demo", action="store_true")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp())
    with simulated_cage(tmp) as rig_toml:
        proc_path = tmp / "orbit.yaml"
        proc_path.write_text(PROCEDURE.format(seconds=args.seconds))
        outcome = Runner(
            parse_procedure(proc_path), load_rig_config(rig_toml), tmp / "runs", quiet=True
        ).run()
    reader = RunReader(outcome.folder)
    meta = reader.meta()
    period_ms = 1000.0 / 50
    print(
        f"orbit replay: {outcome.status}, {meta['commands_scheduled']} field commands at 50 Hz over {args.seconds:.0f} s"
    )
    print(f"lateness p50 {meta['command_lateness_p50_ms']:.2f} ms, p99 {meta['command_lateness_p99_ms']:.2f} ms,"
          f" max {meta['command_lateness_max_ms']:.1f} ms; p99 = {meta['command_lateness_p99_ms'] / period_ms:.3f}"
          f" of the {period_ms:.0f} ms period (target p99 <= 2 ms)")  # fmt: skip
    lost_total = 0
    for dev, (received, expected, rate, gaps) in sample_gaps(reader).items():
        lost_total += gaps
        print(f"{dev}: {received} samples during the replay, {expected:.0f} expected at {rate:.1f} Hz,"
              f" {gaps} gaps longer than 1.5 periods")  # fmt: skip
    reader.close()
    ok = meta["command_lateness_p99_ms"] <= 2.0 and lost_total == 0 and outcome.status == "complete"
    if not args.skip_demo:
        t_demo = time.monotonic()
        demo = subprocess.run(
            [sys.executable, "-m", "rig.cli", "-q", "demo", "--runs-dir", str(tmp / "demo")]
        )
        wall = time.monotonic() - t_demo
        print(
            f"rig demo: exit {demo.returncode}, {wall:.0f} s wall ({wall / 120:.2f} of the 2-minute target)"
        )
        ok = ok and demo.returncode == 0 and wall < 120
    print("PASS" if ok else "MISS")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
