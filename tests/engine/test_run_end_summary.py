"""Every way a run ends says and records what became of the outputs (as read back), where the
data are and how to get the report (issue 33: Ctrl-C printed only 'aborted (...)')."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from rig.cli.run import summarize
from rig.store import RunReader
from tests.simrun import TINY_PROCEDURE, run_on_sim

pytestmark = pytest.mark.simcage


def test_the_end_of_a_run_says_the_outputs_are_off_and_how_to_get_the_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    outcome = run_on_sim(tmp_path, TINY_PROCEDURE)  # no report step
    assert outcome.status == "complete", outcome.reason
    assert re.fullmatch(r"outputs: read back off: coil_x 0\.0[01]\d A, coil_y 0\.0[01]\d A, .*,"
                        r" heater 0\.0[01]\d A, polarity normal", outcome.outputs), outcome.outputs  # fmt: skip
    reader = RunReader(outcome.folder)
    try:
        events = [m for _, level, m in reader.events() if level == "info"]
    finally:
        reader.close()
    assert outcome.outputs in events  # recorded in the run, not only printed
    summarize(outcome, quiet=False)
    out = capsys.readouterr().out
    assert outcome.outputs in out
    assert f"report: not written; write it with: rig report {outcome.folder}" in out
    assert f"data:   {outcome.folder / 'run.sqlite'}" in out
