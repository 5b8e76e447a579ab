"""Procedure files: validation errors cite file, line and step; plans and dry runs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rig.procedure.language import ProcedureError, parse_procedure
from rig.procedure.plan import RigTiming, compile_plan, dry_run, fibonacci_directions
from rig.procedure_files import PROCEDURES_DIR


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "p.yaml"
    p.write_text(text)
    return p


HEAD = "procedure: T\nparameters:\n  dut_serial: {default: A1}\nloads: [bus]\nsteps:\n"


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (
            "  - hold: {hold_s: 2}\n  - sphere_sweep: {direction: 10}\n",
            r"p.yaml:7: step 2 \(sphere_sweep\): sphere_sweep has no parameter 'direction' \(did you mean 'directions'\?\)",
        ),
        (
            "  - hodl: {hold_s: 2}\n",
            r"p.yaml:6: step 1: unknown step or key 'hodl' \(did you mean 'hold'\?\)",
        ),
        (
            "  - hold: {hold_s: -1}\n",
            r"p.yaml:6: step 1 \(hold\): 'hold_s' must be within 0..86400",
        ),
        ("  - set_field: {field_ut: [1, 2]}\n", r"'field_ut' must be a list of 3 numbers"),
        (
            "  - prompt: 'mount {dut_serail}'\n",
            r"unknown parameter '\{dut_serail\}' \(did you mean 'dut_serial'\?\)",
        ),
        (
            "  - hold: {hold_s: 1}\n    loads:\n      buss: {constant: {current_a: 1}}\n",
            r"load 'buss' is not in the procedure's 'loads' list \(did you mean 'bus'\?\)",
        ),
        (
            "  - hold: {hold_s: 1}\n    loads:\n      bus: {sqaure: {high_a: 1, period_s: 1}}\n",
            r"unknown profile 'sqaure' \(did you mean 'square'\?\)",
        ),
        (
            "  - check: {criteria: [{result: x, value: y}]}\n",
            r"a criterion needs result, value and min and/or max",
        ),
        ("  - hold: {hold_s: 1\n", r"p.yaml:\d+: YAML syntax"),
        (
            "  - live_calibrate: {targets: {bias_ut: 30}}\n",
            r"p.yaml:6: step 1 \(live_calibrate\): unknown target 'bias_ut' \(did you mean 'bias_nt'\?\)",
        ),
        ("  - live_calibrate: {targets: {scale: -1}}\n", r"target 'scale' must be a positive"),
        ("  - live_calibrate: {targets: {k_ut_per_a: 0.1}}\n", r"'k_ut_per_a' needs 'telemetry'"),
        ("  - live_calibrate: {}\n", r"stop_on_target needs 'targets'"),
        (
            "  - live_calibrate: {telemetry: [buss], stop_on_target: no}\n",
            r"telemetry 'buss' is not in the procedure's 'loads' list \(did you mean 'bus'\?\)",
        ),
        (
            "  - live_calibrate: {targets: {scale: 1}, min_s: 9, max_s: 5}\n",
            r"min_s must not exceed max_s",
        ),
    ],
)
def test_errors_name_file_line_step_and_fix(tmp_path: Path, body: str, message: str) -> None:
    with pytest.raises(ProcedureError, match=message):
        parse_procedure(write(tmp_path, HEAD + body))


def test_set_overrides_and_unknown_set(tmp_path: Path) -> None:
    p = write(tmp_path, HEAD + "  - prompt: 'mount {dut_serial}'\n")
    assert parse_procedure(p, {"dut_serial": "Z9"}).steps[0].params["text"] == "mount Z9"
    with pytest.raises(ProcedureError, match="no parameter 'operator'"):
        parse_procedure(p, {"operator": "x"})


def test_no_code_execution(tmp_path: Path) -> None:
    p = write(tmp_path, HEAD + "  - prompt: !!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(ProcedureError, match="YAML syntax"):
        parse_procedure(p)


def test_shipped_procedures_parse_and_check_within_limits() -> None:
    k = np.diag([40.2, 39.1, 41.3])
    b0 = np.array([19.6, 1.2, -44.8])
    for path in PROCEDURES_DIR.glob("*.yaml"):
        proc = parse_procedure(path)
        dr = dry_run(
            proc,
            k,
            b0,
            (2.5, 2.5, 2.5),
            120.0,
            {"load_bus": 6.0, "load_panel": 30.0, "heater": 6.0},
        )
        assert dr.violations == [], (path.name, dr.violations)


def test_load_profiles_and_sweep_plan(tmp_path: Path) -> None:
    body = (
        "  - sphere_sweep: {directions: 20, magnitude_ut: [10, 30], dwell_s: 0.5}\n"
        "    loads:\n"
        "      bus: {square: {low_a: 0, high_a: 2, period_s: 4}}\n"
    )
    plan = next(compile_plan(parse_procedure(write(tmp_path, HEAD + body))))
    assert plan.duration_s == pytest.approx(10.0)
    fields = np.array([c.payload["field_ut"] for c in plan.commands if c.kind == "field"])
    mags = np.linalg.norm(fields, axis=1)
    assert len(fields) == 20 and mags.min() == pytest.approx(10) and mags.max() == pytest.approx(30)
    loads = [(c.t_s, c.payload["current_a"]) for c in plan.commands if c.kind == "load"]
    assert loads[:4] == [(0.0, 2.0), (2.0, 0.0), (4.0, 2.0), (6.0, 0.0)] and loads[-1] == (
        10.0,
        0.0,
    )
    dirs = fibonacci_directions(500)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1) and np.abs(dirs.mean(axis=0)).max() < 0.01


def test_dry_run_reports_violations_with_line(tmp_path: Path) -> None:
    p = write(tmp_path, HEAD + "  - set_field: {field_ut: [0, 0, 90]}\n")
    dr = dry_run(
        parse_procedure(p),
        np.diag([40.0, 40.0, 40.0]),
        np.array([0, 0, -45.0]),
        (2.5, 2.5, 2.5),
        120.0,
    )
    assert (
        len(dr.violations) == 1
        and "p.yaml:6: step 1" in dr.violations[0]
        and "beyond 2.5 A" in dr.violations[0]
    )


def test_empty_set_values_are_refused_unless_the_parameter_allows_empty(tmp_path: Path) -> None:
    head = (
        "procedure: T\nparameters:\n  dut_serial: {default: A1}\n"
        "  note: {default: '', allow_empty: yes}\n  label: {}\nsteps:\n"
        "  - prompt: 'mount {dut_serial} {note} {label}'\n"
    )
    p = write(tmp_path, head)
    with pytest.raises(
        ProcedureError,
        match=r"--set dut_serial= is empty: give a value, e.g. --set dut_serial=VALUE, or leave out --set dut_serial to use the default 'A1'$",
    ):
        parse_procedure(p, {"dut_serial": " "})
    with pytest.raises(
        ProcedureError, match=r"--set label= is empty: give a value, e\.g\. --set label=VALUE$"
    ):
        parse_procedure(p, {"label": ""})
    assert parse_procedure(p, {"note": ""}).steps[0].params["text"] == "mount A1  "


def test_dry_run_counts_a_cage_characterization_and_checks_its_amplitude(tmp_path: Path) -> None:
    p = write(
        tmp_path, HEAD + "  - characterize_cage: {amplitude_a: 3.0, samples: 4, repeats: 1}\n"
    )
    proc = parse_procedure(p)
    quick, slow = dry_run(proc), dry_run(proc, timing=RigTiming(max_slew_a_per_s=1.0))
    assert 14 * (0.2 + 4.5 / 20) < quick.duration_s < slow.duration_s
    assert quick.peak_current_a == [3.0, 3.0, 3.0] and quick.violations == []
    dr = dry_run(proc, np.eye(3) * 40, np.zeros(3), (2.5, 2.5, 2.5), 120.0)
    assert len(dr.violations) == 3 and "amplitude 3 A on axis x is beyond 2.5 A" in dr.violations[0]
