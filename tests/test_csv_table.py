"""The CSV reader: exact values, and a one-line UserInputError for any damage (property tests)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rig.errors import UserInputError
from rig.io.csv_table import read_columns, write_columns

finite = st.floats(allow_nan=False, allow_infinity=False, width=64, min_value=-1e9, max_value=1e9)
garbage = st.sampled_from(["", "abc", "1.2.3", "nan", "inf", "--", "0x1f", "1e", " ", "NaN"])
cells = st.one_of(finite.map(repr), garbage)


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(rows=st.lists(st.lists(cells, min_size=3, max_size=3), min_size=1, max_size=12),
       crlf=st.booleans(), bom=st.booleans())  # fmt: skip
def test_any_content_reads_exactly_or_fails_with_a_line_number(
    tmp_path: Path, rows: list[list[str]], crlf: bool, bom: bool
) -> None:
    nl = "\r\n" if crlf else "\n"
    text = ("\ufeff" if bom else "") + "a,b,c" + nl + nl.join(",".join(r) for r in rows) + nl
    path = tmp_path / "f.csv"
    path.write_text(text, encoding="utf-8", newline="")

    def ok(cell: str) -> bool:
        try:
            return math.isfinite(float(cell))
        except ValueError:
            return False

    all_ok = all(ok(c) for r in rows for c in r)
    if all_ok:
        cols = read_columns(path, ["a", "b", "c"])
        np.testing.assert_array_equal(cols["b"], [float(r[1]) for r in rows])
    else:
        with pytest.raises(UserInputError) as info:
            read_columns(path, ["a", "b", "c"])
        msg = str(info.value)
        assert "\n" not in msg and "line " in msg
        first_bad = next(i for i, r in enumerate(rows) if not all(ok(c) for c in r))
        assert f"line {first_bad + 2}" in msg


def test_round_trip_and_column_subset(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "x.csv"
    write_columns(path, {"t": np.arange(4.0), "m": np.array([1.5, -2.0, 3.25, 0.0])})
    assert read_columns(path, ["m"])["m"].tolist() == [1.5, -2.0, 3.25, 0.0]


def test_comments_semicolons_and_short_rows(tmp_path: Path) -> None:
    path = tmp_path / "s.csv"
    path.write_text("# exported by the bench logger\nx;y\n1;2\n# pause\n3;4\n")
    assert read_columns(path, ["y"])["y"].tolist() == [2.0, 4.0]
    path.write_text("x,y\n1,2\n3\n")
    with pytest.raises(UserInputError, match="line 3: only 1 cells"):
        read_columns(path, ["y"])


def test_empty_and_header_only_files(tmp_path: Path) -> None:
    path = tmp_path / "e.csv"
    path.write_text("")
    with pytest.raises(UserInputError, match="is empty"):
        read_columns(path, ["x"])
    path.write_text("x,y\n")
    with pytest.raises(UserInputError, match="no data rows"):
        read_columns(path, ["x"])


def test_binary_file_and_directory(tmp_path: Path) -> None:
    path = tmp_path / "b.csv"
    path.write_bytes(b"\xff\xfe\x00\x01garbage\x80\x81")
    with pytest.raises(UserInputError, match="not a text CSV"):
        read_columns(path, ["x"])
    with pytest.raises(UserInputError, match="is a directory"):
        read_columns(tmp_path, ["x"])


@pytest.mark.parametrize(("asked", "hint"), [("mx", "mx_ut"), ("MZ", "mz_ut"), ("i_pxx", "i_px")])
def test_a_missing_column_suggests_the_name_with_its_unit_first(
    tmp_path: Path, asked: str, hint: str
) -> None:
    """'mx' for 'mx_ut' was answered with 'i_mx' (issue 33)."""
    path = tmp_path / "d.csv"
    path.write_text("t_s,mx_ut,my_ut,mz_ut,i_mx,i_px\n0,1,2,3,4,5\n")
    with pytest.raises(UserInputError, match=f"did you mean '{hint}'"):
        read_columns(path, [asked])
