"""The ``rig`` command.

One module per command (``rig/cli/<command>.py``: its argparse setup and its handler), listed once
in :data:`COMMANDS`; :func:`main` builds the parser from that list, runs the chosen handler and maps
what it raises to an exit code. Signals and a closed output are handled in :mod:`rig.cli.signals`.

Exit codes: 0 success, 1 unexpected internal error, 2 bad input or a calibration the data cannot
support (one line on stderr naming the problem and the fix), 130 interrupted, 141 the reader of our
output went away.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Protocol

from drivers.errors import DeviceError
from rig import __version__
from rig.cli import (
    cage,
    calibrate,
    check,
    demo,
    design,
    devices,
    example_data,
    export,
    lab,
    report,
    run,
    runs,
    safe,
    serve,
    show,
    sim,
    verify,
)
from rig.cli.common import (
    EXIT_INPUT,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    Parser,
    Subparsers,
)
from rig.cli.signals import (
    EXIT_CLOSED_PIPE,
    allow_interrupt,
    quiet_exit_on_closed_pipe,
    stdout_closed,
)
from rig.errors import RigError

__all__ = [
    "COMMANDS",
    "EXIT_CLOSED_PIPE",
    "EXIT_INPUT",
    "EXIT_INTERNAL",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "build_parser",
    "main",
]


class Command(Protocol):
    """A command module: adds its sub-command (and sets ``func``, its handler) to ``sub``."""

    def add_parser(self, sub: Subparsers, parents: list[Parser]) -> None: ...


COMMANDS: tuple[Command, ...] = (
    calibrate,
    sim,
    run,
    safe,
    check,
    design,
    demo,
    runs,
    show,
    report,
    verify,
    export,
    cage,
    example_data,
    devices,
    serve,
    lab,
)
"""Every command, in the order ``rig --help`` lists them. A new command is a module in
``rig/cli/`` with ``add_parser(sub, parents)`` and one entry here."""


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    parser = Parser(prog="rig", description="Helmholtz-cage magnetometer test rig.")
    parser.add_argument("--version", action="version", version=f"rig {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-q", "--quiet", action="store_true", help="print errors only")
    verbosity.add_argument(
        "-v", "--verbose", action="store_true", help="more detail, tracebacks on internal errors"
    )
    # -q/-v are accepted before or after the subcommand (``rig -q sim`` and ``rig sim -q``).
    common = Parser(add_help=False)
    common_v = common.add_mutually_exclusive_group()
    common_v.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                          help="print errors only")  # fmt: skip
    common_v.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                          help="more detail, tracebacks on internal errors")  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for command in COMMANDS:
        command.add_parser(sub, [common])
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``rig`` command; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)  # --help on a closed pipe: argparse drops the text itself
    allow_interrupt()
    try:
        code: int = args.func(args)
        sys.stdout.flush()  # inside the try: a closed pipe shows up here for short outputs
        return code
    except BrokenPipeError as exc:
        if stdout_closed():
            return quiet_exit_on_closed_pipe()
        return _internal_error(exc, args.verbose)
    except (RigError, DeviceError) as exc:
        print(f"rig: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("rig: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:
        return _internal_error(exc, args.verbose)


def _internal_error(exc: Exception, verbose: bool) -> int:
    """A bug: one line unless the user asked for the traceback."""
    if verbose:
        raise exc
    print(
        f"rig: internal error: {type(exc).__name__}: {exc} (rerun with -v for the traceback"
        " and report it)",
        file=sys.stderr,
    )
    return EXIT_INTERNAL
