"""Read named numeric columns from a CSV file, with one-line errors that say how to fix the file."""

from __future__ import annotations

import csv
import difflib
import io
import math
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np
import numpy.typing as npt

from rig.errors import UserInputError

Array = npt.NDArray[np.float64]


def _header(path: Path, names: list[str] | None = None) -> tuple[int, list[str], str]:
    """Line index of the header, its column names and the delimiter. With ``names`` the file has
    no header: the first data line is at index 0 and must have that many cells."""
    try:
        with path.open(encoding="utf-8-sig", newline="") as fh:
            for index, line in enumerate(fh):
                stripped = line.strip()
                if not stripped or stripped.startswith("#"):
                    continue
                delimiter = next((d for d in (",", ";", "\t") if d in stripped), ",")
                cells = [name.strip() for name in next(csv.reader([stripped], delimiter=delimiter))]
                if names is None:
                    return index, cells, delimiter
                if len(cells) != len(names):
                    raise UserInputError(
                        f"{path} line {index + 1}: {len(cells)} cells, but --columns names"
                        f" {len(names)}: name every column of the file, in order"
                    )
                if not _is_number(cells[0]):
                    raise UserInputError(
                        f"{path} line {index + 1} is a header ({', '.join(cells)}): leave"
                        " --columns out, or remove the header row"
                    )
                return index - 1, list(names), delimiter
    except FileNotFoundError:
        raise UserInputError(f"{path}: no such file: check the path") from None
    except IsADirectoryError:
        raise UserInputError(f"{path} is a directory: give a CSV file") from None
    except UnicodeDecodeError:
        raise UserInputError(
            f"{path} is not a text CSV file (not UTF-8): export it as CSV"
        ) from None
    except PermissionError:
        raise UserInputError(f"{path}: permission denied: check the file's permissions") from None
    raise UserInputError(f"{path} is empty: it needs a header row and data rows")


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


MAX_ABS_VALUE = 1e30
"""Largest magnitude a cell may hold: no reading, current or time is this large, and the fits'
sums of squares and fourth powers overflow not far beyond (a cell of 1e308 was an internal error,
issue 51). A larger value is refused like NaN (or left out with ``--drop-invalid``)."""

BLOCK_BYTES = 8 << 20
"""The file is parsed this many bytes at a time (whole lines) straight into the result array, so
reading takes the result's memory plus one block, whatever the file's size."""


def read_columns(
    path: str | Path, columns: list[str], names: list[str] | None = None
) -> dict[str, Array]:
    """Columns by header name as float arrays (all the same length). ``names``: the file has
    no header row and these are its columns, in order.

    Raises :class:`UserInputError` naming the file, line and column for a missing column,
    a non-numeric or empty cell, NaN, infinity or a value beyond :data:`MAX_ABS_VALUE`, or a file
    without data rows. The arrays are
    the columns of one table (:func:`read_table`), each contiguous.
    """
    table = read_table(path, columns, names)
    return {name: table[:, j] for j, name in enumerate(columns)}


def read_table(path: str | Path, columns: list[str], names: list[str] | None = None) -> Array:
    """The named columns as one (rows, len(columns)) float array in column-major order (each
    column contiguous), parsed block by block (:data:`BLOCK_BYTES`) with numpy's C reader.
    Errors as :func:`read_columns`."""
    path = Path(path)
    header_index, names, delimiter = _header(path, names)
    index = [_column_index(path, col, names) for col in columns]
    with path.open("rb") as fh:
        lines = sum(block.count(b"\n") for block in iter(lambda: fh.read(BLOCK_BYTES), b""))
    out = np.empty((lines + 1, len(columns)), order="F")
    filled, bad_rows = 0, 0
    first_bad: tuple[int, int, float] | None = None
    try:
        with path.open("rb") as fh:
            for _ in range(header_index + 1):
                fh.readline()
            for text in _line_blocks(fh):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)  # a block of comments only
                    block = np.loadtxt(io.StringIO(text), delimiter=delimiter, usecols=index,
                                       comments="#", ndmin=2)  # fmt: skip
                bad = ~(np.abs(block) <= MAX_ABS_VALUE)  # NaN, infinite or beyond the bound
                if bad.any():
                    rows = np.flatnonzero(bad.any(axis=1))
                    if first_bad is None:
                        col = int(np.flatnonzero(bad[rows[0]])[0])
                        first_bad = (filled + int(rows[0]), col, float(block[rows[0], col]))
                    bad_rows += rows.size
                out[filled : filled + block.shape[0]] = block
                filled += block.shape[0]
    except (ValueError, UnicodeDecodeError):
        _raise_bad_cell(path, header_index, names, index, delimiter)
        raise  # pragma: no cover - _raise_bad_cell always raises
    if filled == 0:
        raise UserInputError(f"{path} has a header but no data rows")
    if first_bad is not None:
        line = _data_line_numbers(path, header_index)[first_bad[0]]
        value = first_bad[2]
        what = (
            "value is NaN or infinite"
            if not math.isfinite(value)
            else f"value {value:g} is beyond {MAX_ABS_VALUE:g} in magnitude (MAX_ABS_VALUE: no"
            " reading is that large)"
        )
        raise UserInputError(
            f"{path} line {line}, column '{columns[first_bad[1]]}': {what} ({bad_rows} such"
            " rows): remove or repair those rows, or add --drop-invalid to leave them out"
        )
    return out[:filled]


def _line_blocks(fh: BinaryIO) -> Iterator[str]:
    """The rest of a binary file as text in blocks of whole lines (a leading BOM dropped)."""
    rest = b""
    first = True
    while True:
        chunk = fh.read(BLOCK_BYTES)
        if first:
            chunk = chunk.removeprefix(b"\xef\xbb\xbf")
            first = False
        if not chunk:
            if rest.strip():
                yield rest.decode("utf-8")
            return
        chunk = rest + chunk
        cut = chunk.rfind(b"\n") + 1
        rest = chunk[cut:]
        if cut:
            yield chunk[:cut].decode("utf-8")


def read_valid_rows(
    path: str | Path, columns: list[str], names: list[str] | None = None
) -> tuple[dict[str, Array], list[int]]:
    """Like :func:`read_columns`, but a row with an empty, non-numeric, NaN, infinite or huge
    (beyond :data:`MAX_ABS_VALUE`) cell in
    one of ``columns`` (or too few cells) is left out instead of refused: (columns, line numbers
    of the rows left out). A file with no valid row at all is still an error."""
    path = Path(path)
    header_index, names, delimiter = _header(path, names)
    index = [_column_index(path, col, names) for col in columns]
    rows: list[list[float]] = []
    dropped: list[int] = []
    with path.open(encoding="utf-8-sig", newline="") as fh:
        for number, line in enumerate(fh, start=1):
            if number <= header_index + 1 or not line.strip() or line.lstrip().startswith("#"):
                continue
            cells = next(csv.reader([line.rstrip("\r\n")], delimiter=delimiter))
            try:
                values = [float(cells[i]) for i in index]
            except (IndexError, ValueError):
                dropped.append(number)
                continue
            if all(abs(v) <= MAX_ABS_VALUE for v in values):  # NaN compares False
                rows.append(values)
            else:
                dropped.append(number)
    if not rows:
        raise UserInputError(
            f"{path}: no row has a finite number in every one of {', '.join(columns)}"
            f" ({len(dropped)} rows left out): check the columns and the delimiter"
        )
    data = np.asarray(rows, dtype=float)
    return {name: data[:, j].copy() for j, name in enumerate(columns)}, dropped


def _column_index(path: Path, col: str, names: list[str]) -> int:
    if col not in names:
        # a name given without its unit ('mx' for 'mx_ut') before spelling likeness ('i_mx')
        stems = [n for n in names if n.lower().startswith(col.lower() + "_")]
        close = stems or difflib.get_close_matches(col, names, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise UserInputError(f"{path}: no column '{col}'{hint}; the header has: {', '.join(names)}")
    return names.index(col)


def _data_line_numbers(path: Path, header_index: int) -> list[int]:
    with path.open(encoding="utf-8-sig", newline="") as fh:
        return [
            number
            for number, line in enumerate(fh, start=1)
            if number > header_index + 1 and line.strip() and not line.lstrip().startswith("#")
        ]


def _raise_bad_cell(
    path: Path, header_index: int, names: list[str], index: list[int], delimiter: str
) -> None:
    """Find the first unreadable cell among the wanted columns and raise a precise error."""
    with path.open(encoding="utf-8-sig", newline="") as fh:
        for number, line in enumerate(fh, start=1):
            if number <= header_index + 1 or not line.strip() or line.lstrip().startswith("#"):
                continue
            cells = next(csv.reader([line.rstrip("\r\n")], delimiter=delimiter))
            for i in index:
                if i >= len(cells):
                    raise UserInputError(
                        f"{path} line {number}: only {len(cells)} cells, no value for column"
                        f" '{names[i]}': complete or delete that row"
                    )
                cell = cells[i].strip()
                try:
                    value = float(cell)
                except ValueError:
                    what = "is empty" if not cell else f"'{cell[:20]}' is not a number"
                    raise UserInputError(
                        f"{path} line {number}, column '{names[i]}': {what}: fix or delete that"
                        " row, or add --drop-invalid to leave such rows out"
                    ) from None
                if not math.isfinite(value):
                    raise UserInputError(
                        f"{path} line {number}, column '{names[i]}': value is NaN or infinite:"
                        " remove or repair that row"
                    )
    raise UserInputError(
        f"{path}: cannot read the numeric columns: check the delimiter and quoting"
    )


def columns_text(columns: dict[str, Array], fmt: str = "%.6f") -> str:
    """Equal-length columns as CSV text with a header row (``rig example-data`` writes it through
    :func:`rig.cli.common.write_text`: atomically, never through a link)."""
    names = list(columns)
    data = np.column_stack([columns[n] for n in names])
    buf = io.StringIO()
    np.savetxt(buf, data, delimiter=",", header=",".join(names), comments="", fmt=fmt)
    return buf.getvalue()


def write_columns(path: str | Path, columns: dict[str, Array], fmt: str = "%.6f") -> None:
    """Write equal-length columns as CSV with a header row, atomically and never through a
    symbolic link (:func:`rig.io.output_files.write_output`: a link there is an input error)."""
    from rig.io.output_files import write_output

    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_output(path, columns_text(columns, fmt).encode("utf-8"))
    except OSError as exc:
        raise UserInputError(f"cannot write {path}: {exc.strerror}: choose another path") from None
