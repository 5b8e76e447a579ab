"""``rig sim``: run the simulated cage as a standalone process until Ctrl-C or SIGTERM."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rig.cli.common import Parser, Subparsers


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    sim = sub.add_parser(
        "sim",
        parents=parents,
        help="run the simulated cage (Modbus, serial and I2C devices on loopback)",
        description=(
            "Start the physics-based simulated cage behind the real wire protocols and keep it"
            " running until Ctrl-C or SIGTERM. Listens on loopback and pseudo-terminals only."
        ),
    )
    sim.add_argument(
        "--config", metavar="SIM.toml", help="simulator configuration (default: built-in cage)"
    )
    sim.add_argument(
        "--endpoints-json", type=Path, metavar="FILE", help="write the device endpoints as JSON"
    )
    sim.add_argument(
        "--rig-config",
        type=Path,
        metavar="FILE.toml",
        help="write a rig configuration for the devices",
    )
    sim.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    sim.set_defaults(func=_cmd_sim)


def _cmd_sim(args: argparse.Namespace) -> int:
    return run_sim(args.config, args.endpoints_json, args.rig_config, args.duration, args.quiet)


def run_sim(
    config_path: str | None,
    endpoints_json: Path | None,
    rig_config: Path | None,
    duration_s: float | None,
    quiet: bool,
) -> int:
    """Start the cage, publish its endpoints, wait for a stop request, stop cleanly."""
    import json
    import threading
    import time

    from rig.cli.signals import stop_on_signals
    from rig.errors import UserInputError
    from rig.sim_rig import SIM_PROCESS_STALL_AFTER_S, sim_rig_config
    from sim.cage import SimulatedCage
    from sim.config import DEFAULT_CONFIG, SimConfigError, load_config

    try:
        cfg = load_config(config_path or DEFAULT_CONFIG)
    except SimConfigError as exc:
        raise UserInputError(f"{exc}: fix the file or omit --config for the default cage") from None
    stop = threading.Event()
    with stop_on_signals(stop, interrupt=False):
        cage = SimulatedCage(cfg)
        try:
            endpoints = cage.start()
            text = json.dumps(endpoints, indent=2) + "\n"
            for path, content in (
                (endpoints_json, text),
                (rig_config, sim_rig_config(endpoints, cfg, SIM_PROCESS_STALL_AFTER_S)),
            ):
                if path is not None:
                    try:
                        path.parent.mkdir(parents=True, exist_ok=True)
                        tmp = path.with_suffix(path.suffix + ".tmp")
                        tmp.write_text(content, encoding="utf-8")
                        tmp.replace(path)  # readers never see a half-written file
                    except OSError as exc:
                        raise UserInputError(f"cannot write {path}: {exc.strerror}") from None
            if not quiet:
                _print_started(cfg.source, endpoints, (endpoints_json, rig_config),
                               cage.own_processor)  # fmt: skip
            deadline = None if duration_s is None else time.monotonic() + duration_s
            while not stop.wait(0.2):
                if deadline is not None and time.monotonic() >= deadline:
                    break
        finally:
            cage.stop()
    if not quiet:
        print("simulated cage stopped; all outputs off", flush=True)
    return 0


def _print_started(source: str, endpoints: dict[str, Any], written: tuple[Path | None, ...],
                   own_processor: bool) -> None:  # fmt: skip
    """The lines ``rig sim`` prints once its devices answer."""
    print(f"simulated cage running ({source}); loopback only. Devices:")
    for name, dev in endpoints["devices"].items():
        where = dev.get("path") or f"{dev.get('host', '')}:{dev.get('port', '')}"
        if dev.get("protocol") == "i2c":
            where = f"in-process bus, address 0x{dev['address']:02x}"
        print(f"  {name:<12} {dev['kind']:<14} {dev['protocol']:<11} {where}")
    for path in written:
        if path is not None:
            print(f"wrote {path}")
    if not own_processor:
        print("note: the simulated instruments run at normal CPU priority (not root,"
              " no CAP_SYS_NICE); on a busy computer the rig may see them stall")  # fmt: skip
    print("press Ctrl-C to stop", flush=True)
