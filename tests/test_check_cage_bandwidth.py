"""`rig check --rig` and a run's start hold sine steps to what the cage can do (issue 37): a
frequency_response above the cage's measured bandwidth (the ``cage_response`` result in the cage
record) or faster than the coil supplies may slew is a LIMIT line and exit 1, and a run refuses to
start with it; one the procedure measures first is not held to the older record; with no
measurement yet, a warning."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest

from rig.cli import main
from rig.config import load_rig_config
from rig.errors import UserInputError
from rig.procedure.beyond_cage import refuse_beyond_cage
from rig.procedure.language import parse_procedure
from tests.test_check_cage_model import write

NOW = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
RECORD = {"k_ut_per_a": (40.0 * np.eye(3)).tolist(), "b0_ut": [0.0, 0.0, 0.0], "date": NOW,
          "metrology": {"cage_response": {"limit_hz": {"x": 6.05, "y": 5.8, "z": 6.08},
                                          "bandwidth_hz": {"x": 6.05, "y": 5.8, "z": 6.08},
                                          "date": NOW, "run": "r"}}}  # fmt: skip


def sines(freqs: str, amplitude_ut: float = 5.0, kind: str = "frequency_response") -> str:
    return (f"  - {kind}: {{frequencies_hz: [{freqs}], amplitude_ut: {amplitude_ut},"
            " bias_ut: 20, rate_hz: 50, cycles: 1, min_s: 0}\n    name: sines\n")  # fmt: skip


def check(tmp_path: Path, steps: str, record: dict[str, object] | None,
          capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:  # fmt: skip
    proc, cfg = write(tmp_path, steps, record)
    code = main(["check", str(proc), "--rig", str(cfg)])
    return code, capsys.readouterr().out


def test_a_sine_above_the_measured_bandwidth_is_a_limit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out = check(tmp_path, sines("1, 2, 6"), RECORD, capsys)
    limits = [line for line in out.splitlines() if line.startswith("LIMIT:")]
    assert code == 1 and len(limits) == 1, out
    assert "6 Hz on y beyond the cage's measured bandwidth there (5.8 Hz" in limits[0]
    assert "rig run cage-response" in limits[0]
    code, out = check(tmp_path, sines("1, 2, 5.5"), RECORD, capsys)
    assert code == 0 and "LIMIT" not in out, out


def test_a_sine_faster_than_the_supplies_slew_is_a_limit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # 2 pi 5 Hz x 15 uT / 40 uT/A = 11.8 A/s against 10 A/s
    code, out = check(tmp_path, sines("1, 5", amplitude_ut=15.0), RECORD, capsys)
    assert code == 1 and "needs 11.8 A/s, over the cage's max_slew_a_per_s (10)" in out, out
    # the cage_response step is held to the slew too, never to the bandwidth it measures
    code, out = check(tmp_path, sines("1, 8", kind="cage_response"), RECORD, capsys)
    assert code == 0 and "LIMIT" not in out, out
    code, out = check(tmp_path, sines("1, 5", 15.0, "cage_response"), RECORD, capsys)
    assert code == 1 and "needs 11.8 A/s" in out, out


def test_measured_in_the_same_procedure_or_not_at_all(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    measure = sines("1, 8", kind="cage_response").replace("name: sines", "name: cage")
    code, out = check(tmp_path, measure + sines("1, 7"), RECORD, capsys)
    assert code == 0 and "LIMIT" not in out, out
    unmeasured = {k: v for k, v in RECORD.items() if k != "metrology"}
    code, out = check(tmp_path, sines("1, 7"), unmeasured, capsys)
    assert code == 0 and "LIMIT" not in out
    assert "WARNING: step 'sines' (frequency_response) is held to the cage's cage_response" in out


def test_a_run_refuses_to_start_beyond_the_cage(tmp_path: Path) -> None:
    proc, cfg = write(tmp_path, sines("1, 7"), RECORD)
    with pytest.raises(UserInputError, match=r"p\.yaml: frequency_response 'sines': 7 Hz on x"):
        refuse_beyond_cage(parse_procedure(proc), load_rig_config(cfg))
