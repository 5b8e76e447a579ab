"""Read named numeric columns from a CSV file, with one-line errors that say how to fix the file."""

from __future__ import annotations

import csv
import difflib
import math
import warnings
from pathlib import Path

import numpy as np
import numpy.typing as npt

from rig.errors import UserInputError

Array = npt.NDArray[np.float64]


def _header(path: Path) -> tuple[int, list[str], str]:
    """Line index of the header, its column names and the delimiter."""
    try:
        with path.open(encoding="utf-8-sig", newline="") as fh:
            for index, line in enumerate(fh):
                stripped = line.strip()
                if not stripped or stripped.startswith("#"):
                    continue
                delimiter = next((d for d in (",", ";", "\t") if d in stripped), ",")
                names = [name.strip() for name in next(csv.reader([stripped], delimiter=delimiter))]
                return index, names, delimiter
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


def read_columns(path: str | Path, columns: list[str]) -> dict[str, Array]:
    """Columns by header name as float arrays (all the same length).

    Raises :class:`UserInputError` naming the file, line and column for a missing column,
    a non-numeric or empty cell, NaN or infinity, or a file without data rows.
    """
    path = Path(path)
    header_index, names, delimiter = _header(path)
    index: list[int] = []
    for col in columns:
        if col not in names:
            close = difflib.get_close_matches(col, names, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise UserInputError(
                f"{path}: no column '{col}'{hint}; the header has: {', '.join(names)}"
            )
        index.append(names.index(col))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": see below
            data = np.loadtxt(
                path,
                delimiter=delimiter,
                skiprows=header_index + 1,
                usecols=index,
                comments="#",
                ndmin=2,
                encoding="utf-8-sig",
            )
    except ValueError:
        _raise_bad_cell(path, header_index, names, index, delimiter)
        raise  # pragma: no cover - _raise_bad_cell always raises
    if data.shape[0] == 0:
        raise UserInputError(f"{path} has a header but no data rows")
    bad = ~np.isfinite(data)
    if bad.any():
        bad_row, bad_col = (int(v) for v in np.argwhere(bad)[0])
        line = _data_line_numbers(path, header_index)[bad_row]
        raise UserInputError(
            f"{path} line {line}, column '{columns[bad_col]}': value is NaN or infinite"
            f" ({int(bad.any(axis=1).sum())} such rows): remove or repair those rows"
        )
    return {name: data[:, j].copy() for j, name in enumerate(columns)}


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
                        f"{path} line {number}, column '{names[i]}': {what}: fix or delete that row"
                    ) from None
                if not math.isfinite(value):
                    raise UserInputError(
                        f"{path} line {number}, column '{names[i]}': value is NaN or infinite:"
                        " remove or repair that row"
                    )
    raise UserInputError(
        f"{path}: cannot read the numeric columns: check the delimiter and quoting"
    )


def write_columns(path: str | Path, columns: dict[str, Array], fmt: str = "%.6f") -> None:
    """Write equal-length columns as CSV with a header row."""
    path = Path(path)
    names = list(columns)
    data = np.column_stack([columns[n] for n in names])
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savetxt(path, data, delimiter=",", header=",".join(names), comments="", fmt=fmt)
    except OSError as exc:
        raise UserInputError(f"cannot write {path}: {exc.strerror}: choose another path") from None
