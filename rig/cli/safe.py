"""``rig safe``: switch every supply, load and relay of the rig off now.

The emergency stop works whoever holds the rig's interlock: it does not wait for the holder, but
names it, since a command still running may switch outputs on again."""

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
    from rig.config import load_rig_config
    from rig.engine.interlock import holders
    from rig.engine.session import switch_off_every_output

    cfg = load_rig_config(args.rig, check_text=False)  # an emergency stop: devices only
    by_holder: dict[str, list[str]] = {}
    for name, who in holders(cfg).items():
        by_holder.setdefault(who, []).append(name)
    for who, names in by_holder.items():
        print(f"rig: warning: {', '.join(names)} held by {who}, which may switch them on again;"
              " stop that command too", file=sys.stderr)  # fmt: skip
    done, problems = switch_off_every_output(cfg)
    if not args.quiet:
        print(f"switched off: {', '.join(done) or 'nothing'}")
    hint = (
        "stop the command holding it, then run 'rig safe' again"
        if by_holder
        else "switch it off by hand"
    )
    for p in problems:
        print(f"rig: error: could not switch off {p}; {hint}", file=sys.stderr)
    return EXIT_INPUT if problems else EXIT_OK
