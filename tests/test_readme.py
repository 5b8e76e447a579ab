"""The README's main command works (its `rig` steps, run in a scratch folder)."""

from __future__ import annotations

import json
import os
import re
import shlex
from pathlib import Path

import pytest

from rig.cli import main
from tests.conftest import INSTALLED_ENV

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _block(marker: str) -> str:
    text = README.read_text()
    match = re.search(rf"<!-- {marker} -->\s*```sh\n(.*?)\n```\s*<!-- /{marker} -->", text, re.S)
    assert match, f"README lacks the {marker} block"
    return match.group(1).strip()


def test_readme_has_exactly_two_commands() -> None:
    for marker in ("main-command", "test-command"):
        assert "\n" not in _block(marker), f"{marker} must be one line"
    assert "pytest" in _block("test-command")


def test_main_command_is_the_demo() -> None:
    """The main command runs `rig demo`; tests/engine/test_runs_e2e.py runs the demo itself."""
    steps = [s.strip() for s in _block("main-command").split("&&")]
    rig_steps = [shlex.split(s)[1:] for s in steps if s.startswith(".venv/bin/rig ")]
    assert rig_steps == [["demo"]]
    from rig.cli import build_parser

    assert build_parser().parse_args(rig_steps[0]).func.__name__ == "_cmd_demo"


def test_csv_example_rig_steps(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    steps = [s.strip() for s in _block("csv-example").split("&&")]
    rig_steps = [shlex.split(s)[1:] for s in steps if s.startswith(".venv/bin/rig ")]
    assert len(rig_steps) == 2
    for argv in rig_steps:
        assert main(argv) == 0
    out = capsys.readouterr().out
    assert "k[i_eps].z" in out and "chi2/dof" in out
    result = json.loads((tmp_path / "runs/example/result.json").read_text())
    assert result["model"] == "scalar" and abs(result["residual_rms_nt"] / 100 - 1) < 0.1
    assert (tmp_path / "runs/example/magcal.h").read_text().startswith("/* magcal")


def test_the_readme_states_the_number_of_tests_there_are() -> None:
    """The README's test counts and docs/testing.md's per tier are checked, not remembered (it
    said 631 when there were 634; the tier table said 103 simulated-cage tests when there were
    104)."""
    import subprocess
    import sys
    from collections import Counter

    from tests.conftest import TIERS
    from tests.test_tiers import module_tiers

    stated = re.search(r"(\d+) tests\.\nEvery test is in one tier", README.read_text())
    quick = re.search(r"\*\*quick\*\* \((\d+) tests", README.read_text())
    assert stated and quick, "the README no longer states the number of tests and quick ones"
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"],
        cwd=README.parent, capture_output=True, text=True, timeout=300,
        env={k: v for k, v in os.environ.items() if k != INSTALLED_ENV},  # counting only
    )  # fmt: skip
    ids = [line for line in proc.stdout.splitlines() if "::" in line]
    assert ids, proc.stdout[-500:] + proc.stderr[-500:]
    tiers = {path.relative_to(README.parent).as_posix(): marks & set(TIERS)
             for path, marks in module_tiers().items()}  # fmt: skip
    counted = Counter(next(iter(tiers[i.split("::")[0]] or {"quick"})) for i in ids)
    table = (README.parent / "docs" / "testing.md").read_text(encoding="utf-8")
    said = {m.group(1): int(m.group(2)) for m in re.finditer(r"^\| [^|]+ \| `(\w+)` \|[^|]+\| (\d+) \|", table, re.M)}  # fmt: skip
    wrong = []  # both files' counts in one message
    if (int(stated.group(1)), int(quick.group(1))) != (len(ids), counted["quick"]):
        wrong.append(f"README says {stated.group(1)} tests, {quick.group(1)} quick; pytest"
                     f" collects {len(ids)}, {counted['quick']} quick")  # fmt: skip
    if said != dict(counted):
        wrong.append(f"docs/testing.md's tier table says {said}; collected {dict(counted)}")
    assert not wrong, "; ".join(wrong) + ": update it"


def test_the_demo_time_the_readme_states_is_the_one_last_measured() -> None:
    """README's demo time comes from bench/bench_verdict_under_load.py's record
    (bench/results/demo_time.json), idle and beside a second demo and two CPU hogs: a figure
    that cannot drift from its measurement."""
    import json

    record = json.loads((ROOT / "bench" / "results" / "demo_time.json").read_text())
    (lo, hi), (llo, lhi) = record["idle_s"], record["loaded_s"]
    stated = (f"About {lo}-{hi} s on an idle 2-core machine (measured {record['date']} by"
              f" bench/bench_verdict_under_load.py; {llo}-{lhi} s beside a second demo and two"
              " CPU hogs)")  # fmt: skip
    assert stated in " ".join(README.read_text().split()), stated
