"""Text that lands in a run's record (rig.text): control characters and overlong labels are refused
in one line, exit 2, by the procedure language (file:line), ``--set`` and the rig configuration
(issue 29: a NUL byte in a procedure name or serial broke every later lab sync; a 300-character
serial was an internal error, exit 1)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from rig.config import load_rig_config
from rig.errors import UserInputError
from rig.procedure.language import ProcedureError, parse_procedure
from rig.text import MAX_TEXT_CHARS, is_control, is_invisible, shown, text_problem

RIG = [sys.executable, "-m", "rig.cli"]

PROCEDURE = (
    "procedure: {title}\n"  # line 1
    "description: {description}\n"  # line 2
    "parameters:\n"
    "  dut_serial: {{default: {serial}}}\n"  # line 4
    "  lot: {{default: {lot}}}\n"  # line 5
    "  operator: {{default: ana}}\n"
    "magnetometers: {{dut: {dut}, reference: reference}}\n"  # line 7
    "steps:\n"
    "  - prompt: {prompt}\n"  # line 9
    "  - null_field: {{hold_s: 1}}\n"  # line 10
    "    name: {step}\n"  # line 11
    "  - check:\n"
    "      criteria:\n"
    "        - {{result: '{step_ref}', value: dut_noise_nt, max: 200, name: {criterion}}}\n"  # 14
)
GOOD = {"title": "T", "description": "a test", "serial": "SN-1", "lot": "7", "dut": "dut",
        "prompt": "Mount {dut_serial}", "step": "noise floor", "step_ref": "noise floor",
        "criterion": "noise"}  # fmt: skip


def procedure(folder: Path, **fields: str) -> Path:
    path = folder / "p.yaml"
    path.write_text(PROCEDURE.format(**(GOOD | fields)), encoding="utf-8")
    return path


def rig_check(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*RIG, "check", *argv], capture_output=True, text=True, timeout=60)


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "internal error" not in err, err
    return lines[0]


@pytest.mark.parametrize(
    ("field", "value", "line"),
    [
        ("title", '"Accept\\0ance"', 1),
        ("serial", '"SN\\0001"', 4),
        ("lot", '"7\\x1b[31m"', 5),
        ("dut", '"du\\x7ft"', 7),
        ("step", '"noise\\tfloor"', 10),  # a step's name: the step's line
        ("criterion", '"noise\\u0085"', 14),
        ("prompt", '"Mount\\0 it"', 9),
        ("description", '"a\\0b"', 2),
    ],
)
def test_control_characters_are_refused_with_file_and_line(
    tmp_path: Path, field: str, value: str, line: int
) -> None:
    path = procedure(tmp_path, **{field: value})
    done = rig_check(str(path))
    assert done.returncode == 2
    err = one_line(done.stderr)
    assert f"{path}:{line}: " in err and "control character" in err, err
    assert not any(is_control(c) for c in err), err  # shown escaped, never raw


def test_free_text_keeps_tab_and_line_feed_and_labels_do_not(tmp_path: Path) -> None:
    path = procedure(tmp_path, prompt='"Mount it.\\n\\tThen close the door."')
    proc = parse_procedure(path)
    assert proc.steps[0].params["text"] == "Mount it.\n\tThen close the door."
    with pytest.raises(ProcedureError, match=r"p\.yaml:10: .*U\+0009 tab"):
        parse_procedure(procedure(tmp_path, step='"noise\\tfloor"'))


def test_a_300_character_serial_is_refused_in_one_line_exit_2(tmp_path: Path) -> None:
    """`--set`, a default and a name built by substitution; `rig run` refuses it before the rig
    is touched (it was an internal error, exit 1, the code of failed checks)."""
    path = procedure(tmp_path)
    long = "S" * 300
    done = rig_check(str(path), "--set", f"dut_serial={long}")
    assert done.returncode == 2
    assert "300 characters long, beyond the 128" in one_line(done.stderr)
    rig = tmp_path / "rig.toml"
    rig.write_text("")
    runs = tmp_path / "runs"
    ran = subprocess.run([*RIG, "run", str(path), "--rig", str(rig), "--yes", "--runs-dir",
                          str(runs), "--set", f"dut_serial={long}"], capture_output=True,
                         text=True, timeout=60)  # fmt: skip
    assert ran.returncode == 2 and "MAX_TEXT_CHARS" in one_line(ran.stderr)
    assert not runs.exists()
    done = rig_check(str(procedure(tmp_path, serial=long)))
    assert done.returncode == 2 and f"{path}:4: " in one_line(done.stderr)
    # 128 each, within the limit; their substitution into a step name is not
    ok = "S" * MAX_TEXT_CHARS
    assert parse_procedure(procedure(tmp_path, serial=ok)).parameters["dut_serial"] == ok
    with pytest.raises(ProcedureError, match=r"step 2: the step's name .* 257 characters"):
        parse_procedure(procedure(tmp_path, serial=ok, step="'{dut_serial}-{dut_serial}'"))


def test_set_values_with_control_characters_are_refused(tmp_path: Path) -> None:
    path = procedure(tmp_path)
    done = rig_check(str(path), "--set", "operator=ana\x1b]0;pwned\x07")
    assert done.returncode == 2 and "U+001B ESC" in one_line(done.stderr)
    with pytest.raises(ProcedureError, match=r"--set 'dut_serial'='SN\\x00': the value .* NUL"):
        parse_procedure(path, {"dut_serial": "SN\x00"})  # (argv cannot carry a NUL)


RIG_TOML = """
[lab]
rig = {rig}

[devices.{name}]
kind = "riden-rd60xx"
protocol = "modbus-tcp"
host = "127.0.0.1"
port = 502
serial = {serial}

[devices.dut]
kind = "ascii-mag"
protocol = "serial"
path = "/dev/null"
delimiter = "\\t"
"""


def config(folder: Path, name: str = "coil_x", serial: str = '"A-1"', rig: str = '"rig-1"') -> Path:
    path = folder / "rig.toml"
    path.write_text(RIG_TOML.format(name=name, serial=serial, rig=rig))
    return path


@pytest.mark.parametrize(
    ("fields", "where", "problem"),
    [
        ({"serial": '"A\\u0000B"'}, "[devices.coil_x].serial", "U+0000 NUL"),
        ({"serial": '"' + "S" * 300 + '"'}, "[devices.coil_x].serial", "300 characters"),
        ({"name": '"coil\\u0000x"'}, "[devices]: the key 'coil\\x00x'", "U+0000 NUL"),
        ({"rig": '"lab\\u001b"'}, "[lab].rig", "U+001B ESC"),
    ],
)
def test_the_rig_configuration_follows_the_same_rule(
    tmp_path: Path, fields: dict[str, str], where: str, problem: str
) -> None:
    path = config(tmp_path, **fields)
    with pytest.raises(UserInputError) as caught:
        load_rig_config(path)
    assert str(caught.value).startswith(f"{path}: {where}") and problem in str(caught.value)
    done = rig_check(str(procedure(tmp_path)), "--rig", str(path))
    assert done.returncode == 2 and where in one_line(done.stderr)


def test_a_tab_delimiter_and_long_paths_are_fine_in_a_configuration(tmp_path: Path) -> None:
    cfg = load_rig_config(config(tmp_path))
    assert cfg.devices["dut"].get("delimiter") == "\t"
    assert text_problem("/dev/serial/by-id/" + "x" * 200, label=False) is None


def test_file_names_that_land_in_the_record_are_checked_too(tmp_path: Path) -> None:
    """The procedure's file name and the configuration's path are stored in the run."""
    named = tmp_path / "accept\x1bance.yaml"
    named.write_text(procedure(tmp_path).read_text())
    with pytest.raises(ProcedureError, match=r"the file name holds the control character U\+001B"):
        parse_procedure(named)
    cfg = tmp_path / "rig\nlab.toml"
    cfg.write_text(config(tmp_path).read_text())
    with pytest.raises(UserInputError, match=r"the file's path holds .* U\+000A line feed"):
        load_rig_config(cfg)


# --- the rule as a property -----------------------------------------------------------------------

printable = st.text(
    st.characters(blacklist_categories=("Cs",)).filter(
        lambda c: not is_control(c) and not is_invisible(c)
    ),
    max_size=59,
)


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    before=printable,
    bad=st.characters(max_codepoint=0x9F).filter(is_control),
    after=printable,
)
@example(before="SN", bad="\x00", after="1")
def test_any_control_character_in_a_serial_is_refused_and_any_clean_label_is_kept(
    tmp_path: Path, before: str, bad: str, after: str
) -> None:
    """Whatever surrounds it, a control character in a ``--set`` value is refused in one line
    with no control character of its own; the text without it, cut to MAX_TEXT_CHARS, is kept."""
    path = procedure(tmp_path)
    with pytest.raises(ProcedureError) as caught:
        parse_procedure(path, {"dut_serial": before + bad + after})
    message = str(caught.value)
    assert f"at character {len(before) + 1}" in message
    assert not any(is_control(c) for c in message)
    clean = (before + after)[:MAX_TEXT_CHARS]
    if clean.strip():
        assert parse_procedure(path, {"dut_serial": clean}).parameters["dut_serial"] == clean


# --- invisible characters (issue 51): bidi controls and zero-width characters in labels ----------

BIDI = ["\u202a", "\u202b", "\u202c", "\u202d", "\u202e", "\u2066", "\u2067", "\u2068", "\u2069",
        "\u200e", "\u200f", "\u061c"]  # fmt: skip
ZERO_WIDTH = ["\u200b", "\u200c", "\u200d", "\u2060", "\ufeff"]


@pytest.mark.parametrize("ch", BIDI + ZERO_WIDTH)
def test_every_bidi_control_and_zero_width_character_is_refused_in_a_label(ch: str) -> None:
    problem = text_problem(f"SN-1{ch}01")
    assert problem is not None and f"U+{ord(ch):04X}" in problem and "at character 5" in problem
    assert is_invisible(ch)
    assert text_problem(f"Mount the DUT{ch} here", label=False) is None  # free text keeps them


@pytest.mark.parametrize(
    ("field", "value", "line", "name"),
    [
        ("step", '"noise\\u202Efloor"', 10, "U+202E RIGHT-TO-LEFT OVERRIDE"),
        ("serial", '"SN-1\\u200B01"', 4, "U+200B ZERO WIDTH SPACE"),
        ("title", '"Accept\\u2067ance"', 1, "U+2067 RIGHT-TO-LEFT ISOLATE"),
        ("lot", '"7\\uFEFF"', 5, "U+FEFF ZERO WIDTH NO-BREAK SPACE"),
    ],
)
def test_invisible_characters_are_refused_with_file_line_and_name(
    tmp_path: Path, field: str, value: str, line: int, name: str
) -> None:
    path = procedure(tmp_path, **{field: value})
    done = rig_check(str(path))
    assert done.returncode == 2
    err = one_line(done.stderr)
    assert f"{path}:{line}: " in err and name in err, err
    assert not any(is_invisible(c) for c in err), err  # shown escaped, never raw


def test_invisible_characters_in_set_and_the_rig_configuration_are_refused(tmp_path: Path) -> None:
    path = procedure(tmp_path)
    done = rig_check(str(path), "--set", "dut_serial=SN-1\u202e01")
    assert done.returncode == 2 and "RIGHT-TO-LEFT OVERRIDE" in one_line(done.stderr)
    assert "\\u202e" in done.stderr and "\u202e" not in done.stderr
    cfg = config(tmp_path, serial='"A-1\\u200D"')
    with pytest.raises(UserInputError, match=r"\[devices\.coil_x\]\.serial: .*U\+200D ZERO WIDTH"):
        load_rig_config(cfg)
    assert shown("a\u202eb") == "'a\\u202eb'"
