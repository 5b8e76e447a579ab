"""What the command modules share: the parser class, exit codes and small argument helpers.

Nothing here imports numpy or the engine: every ``rig`` invocation imports every command module to
build the parser, so heavy imports belong inside the handlers.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, TypeAlias

from rig.errors import UserInputError

if TYPE_CHECKING:
    from rig.verdict import CriterionResult

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130

Subparsers: TypeAlias = "argparse._SubParsersAction[Parser]"
"""What ``add_subparsers`` returns: a command module's ``add_parser`` adds its sub-command to it."""


class Parser(argparse.ArgumentParser):
    """argparse with the project's one-line error and exit code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_INPUT, f"rig: {message} (see '{self.prog} --help')\n")


def add_runs_dir(parser: argparse.ArgumentParser) -> None:
    """``--runs-dir DIR``, the same on every command that finds runs."""
    parser.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR",
                        help="the folder holding the run folders (default: %(default)s)")  # fmt: skip


def add_run(parser: argparse.ArgumentParser) -> None:
    """The ``RUN`` argument, the same on every command that reads one run."""
    parser.add_argument("run", metavar="RUN",
                        help="a run folder, or a run id under --runs-dir (see 'rig runs')")  # fmt: skip


def columns(text: str) -> list[str]:
    """``A,B,C`` as a list of column names (blanks dropped)."""
    return [c.strip() for c in text.split(",") if c.strip()]


def check_outputs(paths: list[Path | None], *, exclusive: bool = False) -> None:
    """Refuse, before any work, user-named output files :func:`write_text` would refuse (a
    symbolic link, a folder, FIFO or device; with ``exclusive`` any existing file): one line."""
    from rig.io.output_files import check_output

    for path in paths:
        if path is None:
            continue
        try:
            check_output(path, exclusive=exclusive)
        except FileExistsError:
            raise UserInputError(
                f"{path}: exists; choose a new file name (it is not overwritten)"
            ) from None


def write_text(path: Path, text: str, *, exclusive: bool = False) -> None:
    """Write a user-named output file (UTF-8), creating its folder: atomically and never through a
    symbolic link (:func:`rig.io.output_files.write_output`: a link there is refused in one line,
    exit 2). ``exclusive``: an existing file is refused, not overwritten. A failure is a one-line
    input error."""
    from rig.io.output_files import write_output

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_output(path, text.encode("utf-8"), exclusive=exclusive)
    except FileExistsError:
        raise UserInputError(
            f"{path}: exists; choose a new file name (it is not overwritten)"
        ) from None
    except OSError as exc:
        raise UserInputError(f"cannot write {path}: {exc.strerror}: choose another path") from None


def parse_sets(items: list[str]) -> dict[str, str]:
    """``--set name=value`` pairs."""
    out = {}
    for item in items:
        if "=" not in item:
            raise UserInputError(f"--set {item!r}: write --set name=value")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def resolve_run(run: str, runs_dir: Path) -> Path:
    """A run folder by path or id."""
    p = Path(run)
    if (p / "run.sqlite").exists():
        return p
    q = runs_dir / run
    if (q / "run.sqlite").exists():
        return q
    raise UserInputError(f"no run '{run}' (looked at {p} and {q}); list runs with 'rig runs'")


def criterion_value(row: CriterionResult) -> str:
    """A verdict row's value with its unit and limits, or why it has none."""
    if row.value is None:
        return row.reason
    unit = f" {row.unit}" if row.unit else ""
    lo, hi = row.min, row.max
    limits = (
        f"{lo:g}..{hi:g}"
        if lo is not None and hi is not None
        else (f"max {hi:g}" if hi is not None else (f"min {lo:g}" if lo is not None else ""))
    )
    return f"{row.value:.4g}{unit}" + (f"  ({limits})" if limits else "")
