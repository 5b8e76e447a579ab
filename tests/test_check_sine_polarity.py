"""A sine checked with the lab field the coils cancel (issue 51): bias 15 uT, amplitude 10 uT on x
with an ambient of +19.6 uT on x flipped coil x's polarity relay 18 times in 21 s, although
``bias_ut > amplitude_ut`` promises no coil changes polarity mid-sine. `rig check --rig` now
says so (LIMIT, exit 1) and a run refuses to start; without relays, or before the lab field is
measured, there is nothing to say."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest

from rig.cli import main
from rig.config import load_rig_config
from rig.errors import UserInputError
from rig.procedure.language import parse_procedure
from rig.procedure.preflight import refuse_what_check_refuses
from tests.test_check_cage_model import CHARACTERIZE, write

NOW = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
RECORD = {"k_ut_per_a": (40.0 * np.eye(3)).tolist(), "b0_ut": [19.6, 1.2, -44.8], "date": NOW}
RELAYS = ('\n[devices.polarity]\nkind = "regmap-relay"\nprotocol = "modbus-tcp"\nhost = "127.0.0.1"'
          '\nport = 20\nregmap = "relay-h-bridge"\n')  # fmt: skip


def sine(bias_ut: float, amplitude_ut: float = 10.0, axes: str = "x") -> str:
    return (f"  - frequency_response: {{frequencies_hz: [1], amplitude_ut: {amplitude_ut},"
            f" bias_ut: {bias_ut}, axes: {axes}, rate_hz: 20, cycles: 2, min_s: 0}}\n"
            "    name: sines\n")  # fmt: skip


def check(tmp_path: Path, steps: str, capsys: pytest.CaptureFixture[str],
          relays: bool = True) -> tuple[int, list[str], Path, Path]:  # fmt: skip
    proc, cfg = write(tmp_path, steps, RECORD)
    if relays:
        text = cfg.read_text().replace("[cage]\n", '[cage]\npolarity = "polarity"\n')
        cfg.write_text(text + RELAYS)
    code = main(["check", str(proc), "--rig", str(cfg)])
    out = capsys.readouterr().out
    return code, [ln for ln in out.splitlines() if ln.startswith("LIMIT:")], proc, cfg


def test_a_sine_across_the_cancelled_lab_field_is_a_limit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, limits, proc, cfg = check(tmp_path, sine(15.0), capsys)
    assert code == 1 and len(limits) == 1, limits
    assert ("the sine on x (5-25 uT) takes coil x's current through zero at 19.6 uT (the lab"
            " field cancelled): its polarity relay would flip every cycle") in limits[0]  # fmt: skip
    with pytest.raises(UserInputError, match=r"through zero at 19\.6 uT"):
        refuse_what_check_refuses(parse_procedure(proc), load_rig_config(cfg))
    # clear of the crossing on either side; z's lab field is -44.8 uT: a positive bias is clear
    for clear in (sine(35.0), sine(8.0, 2.0), sine(15.0, axes="z")):
        assert check(tmp_path, clear, capsys)[:2] == (0, []), clear


def test_nothing_to_say_without_relays_or_a_known_lab_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert check(tmp_path, sine(15.0), capsys, relays=False)[:2] == (0, [])
    # the cage measured again in the same run, before the sine: its lab field is not known yet
    _, limits, _, _ = check(tmp_path, CHARACTERIZE + sine(15.0), capsys)
    assert not any("through zero" in ln for ln in limits), limits
