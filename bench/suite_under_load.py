"""The test suite on a busy computer: the README's test command N times beside CPU hogs on every
core, and once beside a second copy of itself, against one run on the idle machine measured in
the same invocation (unless --skip-baseline).

Per run it prints passed / failed / errors / skipped, the wall time, its ratio to the idle run,
the machine's mean load average over the run, and the failing tests by name, and at the end how
often the suite passed. Goal (issue 30): every loaded run passes. The hog is `stress-ng --cpu N`
(Debian's stress-ng; N Python busy loops without it, from bench/under_load.py).

Run it from a checkout whose `.venv` has the dev extras installed (the README's test command
builds one); the suite runs in that checkout. `RIG_REQUIRE_TOOLS=1` is set as in CI, so a test
cannot pass by skipping.

Usage: python bench/suite_under_load.py [--runs 3] [--hogs 2] [--skip-baseline] [--skip-pair]
       [--json bench/results/suite_under_load.json] [--repo PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from under_load import cpu_hogs

REPO = Path(__file__).resolve().parent.parent
SUMMARY = re.compile(r"(\d+) (passed|failed|errors?|skipped|xfailed|xpassed|deselected)")


def _test_command(repo: Path) -> list[str]:
    """The pytest part of the README's test command (the venv is assumed built)."""
    text = (repo / "README.md").read_text(encoding="utf-8")
    block = text.split("<!-- test-command -->", 1)[1].split("<!-- /test-command -->", 1)[0]
    pytest_part = block.split("&&")[-1].strip().strip("`").strip()
    return pytest_part.split()


class LoadSampler:
    """Mean of the 1-minute load average, sampled every 10 s while the block runs."""

    def __init__(self) -> None:
        self.values: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(10.0):
            self.values.append(os.getloadavg()[0])

    def __enter__(self) -> LoadSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    @property
    def mean(self) -> float:
        return sum(self.values) / len(self.values) if self.values else os.getloadavg()[0]


def start_suite(repo: Path, log: Path) -> tuple[subprocess.Popen[bytes], float]:
    env = dict(os.environ, RIG_REQUIRE_TOOLS="1")
    cmd = _test_command(repo)
    out = log.open("wb")
    proc = subprocess.Popen(cmd, cwd=repo, env=env, stdout=out, stderr=subprocess.STDOUT)
    return proc, time.monotonic()


def wait_all(procs: list[subprocess.Popen[bytes]]) -> list[float]:
    """Wait for every process; the monotonic time (s) each was seen to end, within 0.5 s (two
    copies end at their own times, not when the first one waited for has)."""
    ended: list[float | None] = [None] * len(procs)
    while any(t is None for t in ended):
        for i, proc in enumerate(procs):
            if ended[i] is None and proc.poll() is not None:
                ended[i] = time.monotonic()
        time.sleep(0.5)
    return [t for t in ended if t is not None]


def finish_suite(
    proc: subprocess.Popen[bytes], started: float, ended: float, log: Path
) -> dict[str, Any]:
    code = proc.wait()
    wall_s = ended - started
    text = log.read_text(encoding="utf-8", errors="replace")
    tail = text.strip().splitlines()[-1] if text.strip() else ""
    counts = {kind.rstrip("s") if kind.startswith("error") else kind: int(n)
              for n, kind in SUMMARY.findall(tail)}  # fmt: skip
    failing = sorted(set(re.findall(r"^(?:FAILED|ERROR) (\S+)", text, re.MULTILINE)))
    return {"exit": code, "wall_s": round(wall_s, 1), "log": str(log), "failing": failing,
            **{k: counts.get(k, 0) for k in ("passed", "failed", "error", "skipped")}}  # fmt: skip


def run_once(repo: Path, label: str, logs: Path, copies: int = 1) -> list[dict[str, Any]]:
    with LoadSampler() as load:
        started = [start_suite(repo, logs / f"{label}-{i}.log") for i in range(copies)]
        ended = wait_all([p for p, _ in started])
        results = [
            finish_suite(p, t, end, logs / f"{label}-{i}.log")
            for i, ((p, t), end) in enumerate(zip(started, ended, strict=True))
        ]
    for r in results:
        r["label"], r["load_mean"] = label, round(load.mean, 1)
    return results


def _print(r: dict[str, Any], idle_s: float | None) -> None:
    ratio = f"{r['wall_s'] / idle_s:5.2f}x" if idle_s else "   -  "
    verdict = "PASS" if r["exit"] == 0 else f"FAIL (exit {r['exit']})"
    print(f"{r['label']:<22} {verdict:<14} {r['passed']:>6} {r['failed']:>6} {r['error']:>6} "
          f"{r['skipped']:>7} {r['wall_s']:>8.0f} {ratio:>7} {r['load_mean']:>6.1f}", flush=True)  # fmt: skip
    for name in r["failing"]:
        print(f"    failing: {name}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument(
        "--runs", type=int, default=3, help="suite runs beside the CPU hogs (default 3)"
    )
    ap.add_argument(
        "--hogs", type=int, default=os.cpu_count() or 2, help="CPU hogs (default: cores)"
    )
    ap.add_argument("--skip-baseline", action="store_true", help="no idle-machine run")
    ap.add_argument("--skip-pair", action="store_true", help="no run beside a second suite")
    ap.add_argument("--repo", type=Path, default=REPO, help="checkout to test (default: this one)")
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args()
    repo = args.repo.resolve()
    logs = repo / "bench" / "results" / "suite-logs"
    logs.mkdir(parents=True, exist_ok=True)
    print(f"suite: {' '.join(_test_command(repo))}  (in {repo})", flush=True)
    print(f"{'run':<22} {'verdict':<14} {'passed':>6} {'failed':>6} {'errors':>6} "
          f"{'skipped':>7} {'wall s':>8} {'vs idle':>7} {'load':>6}", flush=True)  # fmt: skip
    results: list[dict[str, Any]] = []
    idle_s = None
    if not args.skip_baseline:
        (base,) = run_once(repo, "idle", logs)
        idle_s = base["wall_s"]
        results.append(base)
        _print(base, None)
    for i in range(args.runs):
        with cpu_hogs(args.hogs) as hog:
            (r,) = run_once(repo, f"beside {hog.split(' --')[0]} #{i + 1}", logs)
        r["load"] = hog
        results.append(r)
        _print(r, idle_s)
    if not args.skip_pair:
        for r in run_once(repo, "beside a second suite", logs, copies=2):
            results.append(r)
            _print(r, idle_s)
    loaded = [r for r in results if r["label"] != "idle"]
    passed = sum(r["exit"] == 0 for r in loaded)
    print(f"loaded runs passed: {passed} of {len(loaded)}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"results": results}, indent=1) + "\n", encoding="utf-8")
    return 0 if passed == len(loaded) else 1


if __name__ == "__main__":
    sys.exit(main())
