"""``rig safe``: switch every supply, load and relay of the rig off now."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rig.cli.common import EXIT_INPUT, EXIT_OK, Parser, Subparsers


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    safe = sub.add_parser(
        "safe", parents=parents, help="switch every supply, load and relay of the rig off now"
    )
    safe.add_argument(
        "--rig", type=Path, required=True, metavar="CONFIG.toml", help="rig configuration"
    )
    safe.set_defaults(func=_cmd_safe)


def _cmd_safe(args: argparse.Namespace) -> int:
    from rig.engine.guardian import safe_outputs

    done, problems = safe_outputs(args.rig)
    if not args.quiet:
        print(f"switched off: {', '.join(done) or 'nothing'}")
    for p in problems:
        print(f"rig: error: could not switch off {p}; switch it off by hand", file=sys.stderr)
    return EXIT_INPUT if problems else EXIT_OK
