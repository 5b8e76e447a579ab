"""``rig devices scan``: find what is connected to a new bench (rig.bringup does the work).

rig.bringup imports every driver (pymodbus among them, ~0.15 s), so its options are added only
when ``rig devices scan`` is parsed or its help is shown: other commands start without it.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from rig.cli.common import Parser, Subparsers


class _DeferredParser(Parser):
    """A parser whose arguments ``populate`` adds the first time it parses or prints help."""

    def __init__(
        self,
        *args: Any,
        populate: Callable[[argparse.ArgumentParser], None] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        self._populate = populate

    def _ready(self) -> None:
        if self._populate is not None:
            populate, self._populate = self._populate, None
            populate(self)

    def parse_known_args(self, *args: Any, **kwargs: Any) -> Any:
        self._ready()
        return super().parse_known_args(*args, **kwargs)

    def format_help(self) -> str:
        self._ready()
        return super().format_help()

    def format_usage(self) -> str:
        self._ready()
        return super().format_usage()


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    devices = sub.add_parser(
        "devices",
        parents=parents,
        help="find the instruments of a bench and write a rig configuration for them",
        description="Bring-up on a new bench: 'rig devices scan' probes serial ports, I2C buses"
        " and TCP addresses with every registered device kind's identify exchange.",
    )
    dev_sub: Subparsers = devices.add_subparsers(
        dest="devices_command", required=True, parser_class=_DeferredParser
    )
    scan = dev_sub.add_parser(
        "scan",
        parents=parents,
        help="probe ports, buses and hosts; print what answered (--write: a rig configuration)",
        description=(
            "Probe every serial port pyserial lists (plus --port), every I2C bus (plus --i2c-bus)"
            " and every --tcp HOST:PORT with each registered device kind's identify exchange,"
            " print what answered and, with --write FILE, write a rig configuration skeleton."
            " Exit 0 when something answered, 1 when nothing did."
        ),
        populate=_scan_arguments,
    )
    scan.set_defaults(func=_cmd_devices_scan)


def _scan_arguments(parser: argparse.ArgumentParser) -> None:
    from rig.bringup import add_arguments

    add_arguments(parser)


def _cmd_devices_scan(args: argparse.Namespace) -> int:
    from rig.bringup import run

    return run(args)
