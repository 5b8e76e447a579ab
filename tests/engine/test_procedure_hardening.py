"""Procedure files as hostile input: no nan or inf gets through, YAML bombs and oversized files
are refused at once, and files a procedure names stay in its folder (docs/procedures.md, Limits)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings

from bench.fuzz_procedures import Case, cases, check, make_folder
from rig.procedure.language import NotFiniteError, ProcedureError, parse_procedure
from rig.procedure.plan import compile_plan, dry_run
from rig.procedure_files import PROCEDURES_DIR
from rig.steps import load_profiles
from rig.steps.load_profiles import load_profile
from rig.steps.vocabulary import MAX_STEPS, MAX_TOTAL_DURATION_S

HEAD = (
    "procedure: T\n"  # line 1
    "parameters:\n"
    "  h: {default: 2}\n"  # line 3
    "  lim: {default: 60}\n"  # line 4
    "  operator: {default: ana}\n"  # line 5
    "loads: [bus]\n"
    "steps:\n"  # steps start on line 8
)


def write(folder: Path, text: str, name: str = "p.yaml") -> Path:
    p = folder / name
    p.write_text(text, encoding="utf-8")
    return p


# --- non-finite numbers ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("body", "sets", "message"),
    [
        (
            "  - hold: {hold_s: .nan}\n",
            {},
            r"p\.yaml:8: step 1 \(hold\): 'hold_s' is nan; nan, inf",
        ),
        (
            "  - report: {}\n  - set_field: {field_ut: [0, -.inf, 0]}\n",
            {},
            r"p\.yaml:9: step 2 \(set_field\): 'field_ut\[1\]' is -inf",
        ),
        (
            "  - sphere_sweep:\n      directions: 10\n      dwell_s: 1.0e+999\n",
            {},
            r"p\.yaml:10: step 1 \(sphere_sweep\): 'dwell_s' is inf",
        ),
        (
            "  - set_field: {field_ut: [0, 0, " + "9" * 400 + "]}\n",
            {},
            r"p\.yaml:8: step 1 \(set_field\): 'field_ut\[2\]' is 99999999\.\.\. \(400 digits\)",
        ),
        (
            "  - hold: {hold_s: '{h}'}\n",
            {"h": "nan"},
            r"p\.yaml:8: step 1 \(hold\): 'hold_s' must be a finite number, got 'nan' \('\{h\}' is --set h=nan\)",
        ),
        (
            "  - hold: {hold_s: '{h}'}\n",
            {"h": "1e999"},
            r"'hold_s' must be a finite number, got '1e999' \('\{h\}' is --set h=1e999\)",
        ),
        (
            "  - check:\n      criteria:\n        - {result: a, value: b, max: '{lim}'}\n",
            {"lim": "-inf"},
            r"p\.yaml:10: step 1 \(check\): a criterion's 'max' must be a finite number, got '-inf' \('\{lim\}' is --set lim=-inf\)",
        ),
        (
            "  - check:\n      criteria:\n        - {result: a, value: b, min: .nan}\n",
            {},
            r"p\.yaml:10: step 1 \(check\): 'criteria\[0\]\.min' is nan",
        ),
        (
            "  - hold: {hold_s: 4}\n    loads:\n      bus: {steps: {levels_a: [0, .nan], dwell_s: 1}}\n",
            {},
            r"p\.yaml:10: step 1: 'loads\.bus\.steps\.levels_a\[1\]' is nan",
        ),
        (
            "  - hold: {hold_s: 4}\n    loads:\n      bus: {constant: {current_a: '{h}'}}\n",
            {"h": "inf"},
            # load profiles take no placeholders: the text itself is refused, not turned into inf
            r"p\.yaml:8: step 1 load 'bus': 'current_a' must be a number, got '\{h\}'",
        ),
        (
            "  - live_calibrate: {targets: {bias_nt: .inf}}\n",
            {},
            r"p\.yaml:8: step 1 \(live_calibrate\): 'targets\.bias_nt' is inf",
        ),
    ],
)
def test_non_finite_numbers_are_refused_with_file_line_and_parameter(
    tmp_path: Path, body: str, sets: dict[str, str], message: str
) -> None:
    with pytest.raises(ProcedureError, match=message) as err:
        parse_procedure(write(tmp_path, HEAD + body), sets)
    assert "\n" not in str(err.value) and str(err.value).startswith(str(tmp_path))


def test_a_non_finite_parameter_default_is_refused_where_it_is_written(tmp_path: Path) -> None:
    text = HEAD.replace("  h: {default: 2}\n", "  h: {default: .nan}\n") + "  - report: {}\n"
    with pytest.raises(NotFiniteError, match=r"p\.yaml:3: parameter 'h': 'default' is nan"):
        parse_procedure(write(tmp_path, text))
    text = HEAD.replace("  h: {default: 2}\n", "  h: {default: 'inf'}\n")
    with pytest.raises(
        NotFiniteError,
        match=r"p\.yaml:8: step 1 \(hold\): 'hold_s' must be a finite number, got 'inf' \('\{h\}' is the default of parameter 'h' \(.*p\.yaml:3\)\)",
    ):
        parse_procedure(write(tmp_path, text + "  - hold: {hold_s: '{h}'}\n"))


def test_text_that_reads_as_nan_is_still_text_where_text_is_meant(tmp_path: Path) -> None:
    p = write(tmp_path, HEAD + "  - prompt: 'operator {operator}'\n  - hold: {hold_s: '{h}'}\n")
    proc = parse_procedure(p, {"operator": "Nan"})
    assert proc.steps[0].params["text"] == "operator Nan" and proc.steps[1].params["hold_s"] == 2.0


def test_a_parsed_plan_carries_only_finite_numbers(tmp_path: Path) -> None:
    """The crash the tester found: nan passed the checks and ``rig run`` died compiling it."""
    p = write(tmp_path, HEAD + "  - sphere_sweep: {directions: '{h}', dwell_s: 0.5}\n")
    with pytest.raises(NotFiniteError):
        parse_procedure(p, {"h": "nan"})
    plan = next(compile_plan(parse_procedure(p, {"h": "12"})))
    assert len([c for c in plan.commands if c.kind == "field"]) == 12


# --- YAML bombs and sizes -------------------------------------------------------------------------


def billion_laughs(levels: int = 9) -> str:
    rows = ["      - &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n"]
    rows += [f"      - &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]\n" for i in range(1, levels + 1)]
    return (
        "procedure: bomb\nparameters:\n  x:\n    default:\n"
        + "".join(rows)
        + ("steps:\n  - prompt: 'mount {x}'\n")
    )


def test_an_alias_bomb_in_a_parameter_default_is_refused_at_once(tmp_path: Path) -> None:
    p = write(tmp_path, billion_laughs())
    t0 = time.thread_time()  # CPU time of this thread: our work, not the scheduler's
    with pytest.raises(
        ProcedureError,
        match=r"p\.yaml:\d+: more than 500000 values with YAML aliases expanded \(MAX_YAML_NODES",
    ):
        parse_procedure(p)
    assert time.thread_time() - t0 < 1.0  # about 1 ms; was a hang with growing memory


def test_aliases_within_the_limits_still_work(tmp_path: Path) -> None:
    text = (
        HEAD + "  - hold: {hold_s: 2}\n    loads:\n      bus: &profile {constant: {current_a: 1}}\n"
        "  - hold: {hold_s: 3}\n    loads:\n      bus: *profile\n"
    )
    proc = parse_procedure(write(tmp_path, text))
    assert proc.steps[0].loads == proc.steps[1].loads == {"bus": ("constant", {"current_a": 1.0})}
    # 9**3 values pass the YAML limits; as one parameter's value (53 504 characters) it is no
    # label, which the text rule (rig.text) refuses
    with pytest.raises(ProcedureError, match=r"p\.yaml:3: parameter 'x': .* 53504 characters"):
        parse_procedure(write(tmp_path, billion_laughs(3)))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("procedure: T\ndescription: &a [1, *a]\nsteps:\n  - report: {}\n", r"p\.yaml:2: alias \*a is inside the anchor it names"),
        ("procedure: T\ndescription: [&a 1" + ", *a" * 101 + "]\nsteps:\n  - report: {}\n", r"p\.yaml:2: more than 100 YAML aliases \(MAX_YAML_ALIASES\)"),
        ("procedure: T\ndescription: " + "[" * 100_000 + "]" * 100_000 + "\nsteps:\n  - report: {}\n", r"p\.yaml:2: nested more than 32 levels deep \(MAX_YAML_DEPTH\)"),
        ("procedure: T\ndescription: 2001-02-30\nsteps:\n  - report: {}\n", r"p\.yaml:2: YAML value '2001-02-30': day is out of range"),
        ("procedure: T\ndescription: " + "9" * 5000 + "\nsteps:\n  - report: {}\n", r"p\.yaml:2: YAML value '9+': Exceeds the limit \(4300 digits\)"),
        ("procedure: T\nparameters: {x: {default: a}}\nsteps:\n  - prompt: '{x:>999999999}'\n", r"p\.yaml:4: step 1: format '\{\.\.\.:>999999999\}' not allowed"),
    ],
)  # fmt: skip
def test_hostile_yaml_is_refused_with_its_line(tmp_path: Path, text: str, message: str) -> None:
    t0 = time.thread_time()  # CPU time of this thread: our work, not the scheduler's
    with pytest.raises(ProcedureError, match=message):
        parse_procedure(write(tmp_path, text))
    assert time.thread_time() - t0 < 1.0


def test_twenty_thousand_steps_are_refused_quickly_and_ten_thousand_parse(tmp_path: Path) -> None:
    p = write(tmp_path, "procedure: T\nsteps:\n" + "  - hold: {hold_s: 1}\n" * 20_000)
    t0 = time.thread_time()  # CPU time of this thread: our work, not the scheduler's
    with pytest.raises(
        ProcedureError,
        match=rf"p\.yaml:{MAX_STEPS + 3}: step {MAX_STEPS + 1}: a procedure has at most {MAX_STEPS} steps \(MAX_STEPS\)",
    ):
        parse_procedure(p)
    assert time.thread_time() - t0 < 2.0  # about 0.2 s: it stops reading at step 10 001
    p = write(tmp_path, "procedure: T\nsteps:\n" + "  - hold: {hold_s: 1}\n" * MAX_STEPS)
    assert len(parse_procedure(p).steps) == MAX_STEPS


def test_a_million_steps_are_refused_by_the_file_size_before_reading(tmp_path: Path) -> None:
    p = write(tmp_path, "procedure: T\nsteps:\n" + "  - report: {}\n" * 1_000_000)
    t0 = time.thread_time()  # CPU time of this thread: our work, not the scheduler's
    with pytest.raises(
        ProcedureError, match=r"p\.yaml: larger than 1048576 bytes \(MAX_PROCEDURE_FILE_BYTES\)"
    ):
        parse_procedure(p)
    assert time.thread_time() - t0 < 1.0  # was 299 s and 4.1 GB


def test_duration_and_load_set_points_are_bounded_with_the_step(tmp_path: Path) -> None:
    p = write(tmp_path, "procedure: T\nsteps:\n" + "  - hold: {hold_s: 86400}\n" * 8)
    with pytest.raises(
        ProcedureError,
        match=rf"p\.yaml:10: step 8 \(hold\): the procedure's duration reaches 8\.00 days here, beyond the {MAX_TOTAL_DURATION_S / 86400:g}-day limit \(MAX_TOTAL_DURATION_S\)",
    ):
        parse_procedure(p)
    p = write(tmp_path, "procedure: T\nsteps:\n" + "  - hold: {hold_s: 86400}\n" * 7)
    assert dry_run(parse_procedure(p)).duration_s == MAX_TOTAL_DURATION_S
    p = write(
        tmp_path,
        HEAD + "  - hold: {hold_s: 86400}\n    loads: {bus: {ramp: {to_a: 1, step_s: 0.02}}}\n",
    )
    with pytest.raises(
        ProcedureError,
        match=r"p\.yaml:8: step 1 \(hold\): load 'bus': .* more than 1000000 set-points over 86400 s \(MAX_LOAD_SETPOINTS_PER_STEP\)",
    ):
        parse_procedure(p)  # fmt: skip


# --- files a procedure names ----------------------------------------------------------------------


def csv_step(name: str) -> str:
    return (
        HEAD
        + f"  - hold: {{hold_s: 2}}\n    loads:\n      bus: {{csv: {{file: '{name}', column: a}}}}\n"
    )


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    """tmp/proc with profile.csv, nan.csv, sub/x.csv, link.csv -> ../outside.csv, up -> ..,
    inlink.csv -> profile.csv; tmp/outside.csv."""
    return make_folder(tmp_path)


@pytest.mark.parametrize(
    "name", ["../outside.csv", "link.csv", "up/outside.csv", "ABSOLUTE", "/etc/passwd"]
)
def test_a_csv_profile_outside_the_procedure_folder_is_refused(folder: Path, name: str) -> None:
    name = str(folder.parent / "outside.csv") if name == "ABSOLUTE" else name
    with pytest.raises(
        ProcedureError,
        match=r"p\.yaml:8: step 1 \(hold\): load 'bus': file '.*' resolves to .*, outside .*proc: files a procedure names must be in the procedure's folder",
    ):
        parse_procedure(write(folder, csv_step(name)))  # fmt: skip


@pytest.mark.parametrize(
    "name", ["profile.csv", "sub/x.csv", "inlink.csv", "sub/../profile.csv", "INSIDE"]
)
def test_a_csv_profile_inside_the_procedure_folder_is_used(folder: Path, name: str) -> None:
    name = str(folder / "profile.csv") if name == "INSIDE" else name
    plan = next(compile_plan(parse_procedure(write(folder, csv_step(name)))))
    loads = [(c.t_s, c.payload["current_a"]) for c in plan.commands if c.kind == "load"]
    assert loads[0] in ((0.0, 0.5), (0.0, 0.2)) and loads[-1] == (2.0, 0.0)  # fmt: skip


def test_the_folder_rule_holds_at_compile_time_too(folder: Path) -> None:
    """A plan compiled from a step made elsewhere (not through the language) checks again."""
    with pytest.raises(ProcedureError, match="outside"):
        load_profile("csv", {"file": "link.csv", "column": "a"}, 2.0, folder)


def test_csv_profiles_are_bounded_and_finite(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(
        NotFiniteError, match=r"p\.yaml:8: step 1 \(hold\): load 'bus': .*nan\.csv:3: 'a' is 'nan'"
    ):
        parse_procedure(write(folder, csv_step("nan.csv")))
    (folder / "long.csv").write_text("t_s,a\n" + "".join(f"{i * 0.1:g},1\n" for i in range(8)))
    monkeypatch.setattr(load_profiles, "MAX_CSV_PROFILE_ROWS", 5)
    with pytest.raises(
        ProcedureError,
        match=r"long\.csv:7: a CSV load profile may have at most 5 rows \(MAX_CSV_PROFILE_ROWS\)",
    ):
        parse_procedure(write(folder, csv_step("long.csv")))
    monkeypatch.setattr(load_profiles, "MAX_CSV_PROFILE_BYTES", 20)
    with pytest.raises(
        ProcedureError,
        match=r"long\.csv: a CSV load profile may have at most 20 bytes \(MAX_CSV_PROFILE_BYTES\)",
    ):
        parse_procedure(write(folder, csv_step("long.csv")))  # fmt: skip


# --- any text -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def fuzz_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_folder(tmp_path_factory.mktemp("fuzz"))


@settings(max_examples=200, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                 HealthCheck.data_too_large])  # fmt: skip
@given(case=cases())
def test_any_procedure_text_parses_or_is_refused_clearly(fuzz_folder: Path, case: Case) -> None:
    """Parsed: every number in its plan finite, within the limits; refused: a UserInputError of
    one line starting with the file; never another exception, never over 5 s. 10 000 examples:
    bench/fuzz_procedures.py."""
    check(fuzz_folder, case)


def test_field_set_points_of_orbit_replay_and_live_calibration_are_bounded(tmp_path: Path) -> None:
    shipped = PROCEDURES_DIR
    with pytest.raises(
        ProcedureError,
        match=r"4320000 field set-points, more than 1000000 \(MAX_FIELD_SETPOINTS_PER_STEP\)",
    ):  # a day at 50 set-points a second
        parse_procedure(shipped / "orbit-replay.yaml", {"duration_s": "86400"})
    assert parse_procedure(shipped / "orbit-replay.yaml", {"duration_s": "18000"})
    text = (shipped / "live-calibration.yaml").read_text().replace("dwell_s: 0.8", "dwell_s: 0.05")
    live = write(tmp_path, text)
    with pytest.raises(
        ProcedureError,
        match=r"p\.yaml:\d+: .*1728000 field set-points, more than 1000000 \(MAX_FIELD_SETPOINTS_PER_STEP\)",
    ):
        parse_procedure(live, {"max_s": "86400"})
    assert parse_procedure(live, {"max_s": "3600"})  # fmt: skip
