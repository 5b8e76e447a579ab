"""``rig safe``: switch every supply, load and relay of the rig off now, and read each back.

An emergency stop depends on nothing but where the outputs are: each ``[devices.NAME]`` table is
read on its own, and of it only what opens the device (:mod:`rig.engine.safe_targets`); the rest of the
file may be invalid. A file that cannot be parsed at all is replaced by the configuration the
last run used from it (:mod:`rig.engine.config_copy`), said in one line. Every output is read back
after it is switched off, one line each; the exit status is 0 only when every output read back
off, 2 when one could not be confirmed off (each named in one line with the fix).

It works whoever holds the rig's interlock: it does not wait for the holder, but names it, since a
command still running may switch outputs on again."""

from __future__ import annotations

import argparse
import sys
import tomllib
from pathlib import Path
from typing import Any

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
    from rig.config import RigConfig
    from rig.engine.interlock import holders
    from rig.engine.safe_targets import safe_targets
    from rig.engine.switch_off import switch_off_and_confirm

    targets = safe_targets(_parsed(args.rig))
    by_holder: dict[str, list[str]] = {}
    for name, who in holders(RigConfig(args.rig, targets.devices)).items():
        by_holder.setdefault(who, []).append(name)
    for who, names in by_holder.items():
        print(f"rig: warning: {', '.join(names)} held by {who}, which may switch them on again;"
              " stop that command too", file=sys.stderr)  # fmt: skip
    states = switch_off_and_confirm(targets.devices, unreachable=list(targets.broken))
    if not args.quiet:
        for state in states.values():
            print(state.line())
    hint = (
        "stop the command holding it, then run 'rig safe' again"
        if by_holder
        else "switch it off by hand (its mains switch), then check its wiring and address"
    )
    for name, why in targets.broken.items():
        print(f"rig: error: {name}: could not confirm off: its [devices.{name}] table: {why};"
              " then run 'rig safe' again, or switch it off by hand", file=sys.stderr)  # fmt: skip
    unconfirmed = [s for s in states.values() if not s.off]
    for state in unconfirmed:
        print(f"rig: error: {state.line()}; {hint}", file=sys.stderr)
    return EXIT_INPUT if unconfirmed or targets.broken else EXIT_OK


def _parsed(path: Path) -> dict[str, Any]:
    """The rig file's tables; when it cannot be parsed, those of the configuration the last run
    used from it (said in one line on stderr); a UserInputError when there is none."""
    from rig.engine.config_copy import last_config_copy
    from rig.errors import UserInputError

    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        why = f"is not valid TOML ({exc})"
    except RecursionError:
        why = "nests arrays or tables too deep for the TOML parser"
    except UnicodeDecodeError as exc:
        why = f"is not UTF-8 text ({exc.reason} at byte {exc.start})"
    except OSError as exc:
        why = f"cannot be read ({exc.strerror or exc})"
    copy = last_config_copy(path)
    if copy is not None:
        text, where = copy
        try:
            raw = tomllib.loads(text)
        except (tomllib.TOMLDecodeError, RecursionError):
            pass  # not one a run parsed: as if there were none
        else:
            print(f"rig: {path} {why}; switching off the devices of the configuration the last"
                  f" run used ({where})", file=sys.stderr)  # fmt: skip
            return raw
    raise UserInputError(
        f"{path} {why}, and no run on this computer has used it (no copy of it to fall back"
        " on): fix the file and run 'rig safe' again, or switch the outputs off by hand"
    )
