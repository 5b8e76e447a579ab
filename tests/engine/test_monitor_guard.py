"""The health monitor cannot die silently (issue 32's safety hole): a failure inside it ends the
run safely with a one-line reason, and a bad ``stuck_after`` never reaches it."""

from __future__ import annotations

from pathlib import Path

import pytest

from rig.config import load_rig_config
from rig.engine.health import HealthMonitor
from rig.errors import UserInputError
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage

HOLD = """
procedure: Hold
magnetometers: {dut: dut, reference: reference}
steps:
  - null_field: {hold_s: 20}
"""


def test_a_monitor_that_fails_ends_the_run_safely(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rounds = [0]
    check = HealthMonitor.check

    def failing(self: HealthMonitor, *args: object, **kwargs: object) -> None:
        rounds[0] += 1
        if rounds[0] == 5:  # a second into the run, with the coils on
            raise ValueError("invalid literal for int() with base 10: 'abc'")
        check(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(HealthMonitor, "check", failing)
    outcome = run_on_sim(tmp_path, HOLD)
    assert outcome.status == "error", outcome.reason
    assert outcome.reason.startswith("the health monitor stopped (ValueError: invalid literal")


@pytest.mark.parametrize("value", ['"abc"', "-1", "2.5"])
def test_a_bad_stuck_after_is_refused_when_the_configuration_loads(
    tmp_path: Path, value: str
) -> None:
    cfg = tmp_path / "rig.toml"
    cfg.write_text(
        f'[devices.dut]\nkind = "hmr2300"\nprotocol = "serial"\npath = "/dev/null"\nstuck_after = {value}\n'
    )
    with pytest.raises(UserInputError, match=r"\[devices\.dut\]\.stuck_after"):
        load_rig_config(cfg)
