"""A check criterion names a step before it and a value that step's kind records; a typo is
refused when the procedure is read (by `rig check` and before `rig run` switches anything on),
with the valid names, not found after the whole run (issue 33)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rig.procedure.language import parse_procedure
from rig.procedure_files import PROCEDURES_DIR, find_procedure
from rig.steps.vocabulary import ProcedureError

SHIPPED = PROCEDURES_DIR

PROCEDURE = """
procedure: typo hunt
magnetometers: {{dut: dut, reference: reference}}
steps:
  - null_field: {{hold_s: 1}}
    name: noise floor
  - calibrate: {{model: vector}}
    name: vector calibration
  - check:
      criteria:
        - {{result: {result}, value: {value}, max: 60, name: the criterion}}
"""


def parse(tmp_path: Path, result: str, value: str) -> None:
    (tmp_path / "p.yaml").write_text(PROCEDURE.format(result=result, value=value))
    parse_procedure(tmp_path / "p.yaml")


@pytest.mark.parametrize(("result", "value"), [
    ("noise floor", "dut_noise_nt"), ("noise floor", "reference_paired_noise_nt"),
    ("vector calibration", "residual_rms_nt"), ("vector calibration", "springmann.a"),
    ("vector calibration", "angular_uncertainty_deg.50_ut"),
])  # fmt: skip
def test_names_the_steps_record_are_accepted(tmp_path: Path, result: str, value: str) -> None:
    parse(tmp_path, result, value)


def test_a_misspelt_value_is_refused_with_the_valid_names(tmp_path: Path) -> None:
    with pytest.raises(ProcedureError) as exc:
        parse(tmp_path, "vector calibration", "residual_rms")
    text = str(exc.value)
    assert "p.yaml:11: step 3 (check): criterion 'the criterion'" in text
    assert "records no 'residual_rms' (did you mean 'residual_rms_nt'?)" in text
    assert "it records: residual_rms_nt, residual_mean_nt" in text


def test_a_noise_value_without_its_unit_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ProcedureError, match=r"records no 'dut_noise'; it records: \*_noise_nt"):
        parse(tmp_path, "noise floor", "dut_noise")


def test_a_result_that_no_earlier_step_has_is_refused(tmp_path: Path) -> None:
    with pytest.raises(
        ProcedureError,
        match=r"no step named 'noise flor' before it \(did you mean"
        r" 'noise floor'\?\) \(steps before it: noise floor, vector calibration\)",
    ):
        parse(tmp_path, "noise flor", "dut_noise_nt")


@pytest.mark.parametrize("name", sorted(p.stem for p in SHIPPED.glob("*.yaml")))
def test_every_shipped_procedure_names_what_its_steps_record(name: str) -> None:
    parse_procedure(find_procedure(name))
