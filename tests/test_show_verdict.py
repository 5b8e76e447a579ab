"""``rig show`` says why a run has no verdict: not yet judged while running, not judged when
aborted, no check step only for a finished run without one."""

from __future__ import annotations

from rig.cli.show import verdict_line
from rig.store.run_states import Verdict
from rig.verdict import CheckVerdict


def test_verdict_line_says_why_there_is_none() -> None:
    assert verdict_line("running", None) == "VERDICT: not yet judged (running)"
    assert verdict_line("aborted", None) == "VERDICT: not judged (aborted)"
    assert verdict_line("complete", None) == "VERDICT: - (no check step)"
    assert verdict_line("aborted", CheckVerdict((), Verdict.FAIL)) == "VERDICT: FAIL"
