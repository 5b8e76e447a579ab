"""``rig devices scan``: find what is connected to a new bench and write a rig configuration for it.

Looks at every serial port pyserial lists (plus ``--port PATH``), every I2C bus ``/dev/i2c-N``
(plus ``--i2c-bus N``) and every ``--tcp HOST:PORT`` given, and tries each registered device kind's
identify exchange there (``drivers.registry``: the Riden model id register, a register map's model
register, the HMR2300's ``*99ID=``, the RM3100's revision id, a text line of three numbers, ...),
with short timeouts. It prints a table of what answered and, with ``--write FILE``, a rig
configuration skeleton (TOML) for it: the devices are complete, the cage section is for the user
to check and fill in.

    rig devices scan --port /dev/ttyUSB0 --tcp 192.168.1.50:502 --write rig.toml
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.errors import DeviceError, DeviceRefusedError
from drivers.registry import KINDS, DeviceKind, Found, ProbeTarget, transport_param
from drivers.transport.modbus import ModbusLink
from rig.config import load_rig_config
from rig.errors import UserInputError
from rig.io.output_files import check_output, write_output

MODBUS = ("modbus-rtu", "modbus-tcp")
NAME_PREFIX = {"supply": "psu", "load": "load", "relay": "polarity", "magnetometer": "mag",
               "scalar": "scalar", "thermometer": "temp"}  # fmt: skip


@dataclass(frozen=True)
class Unknown:
    """A place where a Modbus device answered but no registered kind recognized it."""

    protocol: str
    params: dict[str, Any]
    where: str
    registers: tuple[int, ...] = ()
    """Holding registers 0-3 as read (empty if the device refused the read)."""

    def describe(self) -> str:
        """What the table says of it: the registers it read, and a Riden-like model id named."""
        if not self.registers:
            return "a Modbus device of no known model"
        regs = " ".join(str(r) for r in self.registers)
        if 60000 <= self.registers[0] <= 60999:
            return (f"Riden-like model id {self.registers[0]} not in the known RD60xx table"
                    f" (registers 0-3: {regs})")  # fmt: skip
        return f"a Modbus device of no known model (registers 0-3: {regs})"


def serial_ports(extra: Iterable[str] = (), *, listed: bool = True) -> list[str]:
    """Serial ports pyserial lists (when ``listed``) and the ``extra`` ones, each once."""
    ports: list[str] = []
    if listed:
        from serial.tools import list_ports

        ports = [p.device for p in list_ports.comports()]
    out: list[str] = []
    seen: set[str] = set()
    for port in [*extra, *ports]:
        key = os.path.realpath(port) if "://" not in port else port
        if key not in seen:
            seen.add(key)
            out.append(port)
    return out


def i2c_buses(extra: Iterable[int] = (), *, listed: bool = True) -> list[int]:
    """Bus numbers of ``/dev/i2c-N`` (when ``listed``) and the ``extra`` ones, each once."""
    found = []
    if listed:
        for path in glob.glob("/dev/i2c-*"):
            m = re.fullmatch(r"/dev/i2c-(\d+)", path)
            if m:
                found.append(int(m.group(1)))
    return sorted(set(found) | set(extra))


def parse_tcp(text: str) -> tuple[str, int]:
    """``HOST:PORT`` to (host, port); a user error names the fix."""
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise UserInputError(f"--tcp {text}: write HOST:PORT, e.g. --tcp 192.168.1.50:502")
    rule = transport_param("modbus-tcp", "port")
    if rule.problem(int(port)) is not None:
        raise UserInputError(
            f"--tcp {text}: port {int(port)} is outside {rule.accepted} (a TCP port); write the"
            " port the device listens on, e.g. --tcp 192.168.1.50:502"
        )
    return host, int(port)


def _serial_order(kind: DeviceKind) -> int:
    """Passive listening first, then Modbus requests (devices resynchronize on silence), then
    text commands."""
    if kind.probe_first:
        return 0
    return 1 if any(t in MODBUS for t in kind.transports) else 2


def _targets_for_port(path: str, timeout_s: float) -> list[tuple[DeviceKind, ProbeTarget]]:
    out = []
    for kind in sorted(KINDS.values(), key=_serial_order):
        if kind.probe is None:
            continue
        protocol = "modbus-rtu" if "modbus-rtu" in kind.transports else "serial"
        if protocol not in kind.transports:
            continue
        for baud in kind.probe_baudrates:
            params: dict[str, Any] = {"path": path, "baudrate": baud}
            if protocol == "modbus-rtu":
                params["device_id"] = 1
            out.append((kind, ProbeTarget(protocol, params, timeout_s)))
    return out


def _modbus_answers(
    protocol: str, params: dict[str, Any], timeout_s: float
) -> tuple[int, ...] | None:
    """Does anything answer a Modbus read of holding registers 0-3 (values or an exception)?
    Returns the registers read (empty if refused), or None when nothing answered."""
    try:
        if protocol == "modbus-tcp":
            link = ModbusLink(name="scan", host=params["host"], port=params["port"],
                              timeout_s=timeout_s, retries=0)  # fmt: skip
        else:
            link = ModbusLink(name="scan", path=params["path"], baudrate=params["baudrate"],
                              timeout_s=timeout_s, retries=0)  # fmt: skip
    except DeviceError:
        return None
    try:
        return tuple(link.read_registers(0, 4))
    except DeviceRefusedError:
        return ()
    except DeviceError:
        return None
    finally:
        link.close()


def scan(
    ports: Iterable[str] = (),
    buses: Iterable[int | str] = (),
    tcp: Iterable[tuple[str, int]] = (),
    *,
    timeout_s: float = 0.2,
    i2c_objects: dict[str, Any] | None = None,
    progress: Callable[[str], None] | None = None,
) -> tuple[list[Found], list[Unknown]]:
    """Probe every place; returns what answered and the Modbus devices nobody recognized.

    ``buses`` are bus numbers, or names of ``i2c_objects`` (an smbus2-compatible object, such as
    the simulator's in-process bus under ``"sim"``).
    """
    found: list[Found] = []
    unknown: list[Unknown] = []
    say = progress or (lambda _m: None)
    for path in ports:
        say(f"serial port {path}")
        hit: list[Found] = []
        for kind, target in _targets_for_port(path, timeout_s):
            assert kind.probe is not None
            hit = kind.probe(target)
            if hit:
                break
        found += hit
        if not hit:
            for baud in sorted({b for k in KINDS.values() if "modbus-rtu" in k.transports
                                for b in k.probe_baudrates}):  # fmt: skip
                params = {"path": path, "baudrate": baud, "device_id": 1}
                regs = _modbus_answers("modbus-rtu", params, timeout_s)
                if regs is not None:
                    unknown.append(Unknown("modbus-rtu", params, path, regs))
                    break
    for host, port in tcp:
        where = f"{host}:{port}"
        say(f"Modbus TCP {where}")
        params = {"host": host, "port": port, "device_id": 1}
        hit = []
        for kind in KINDS.values():
            if kind.probe is not None and "modbus-tcp" in kind.transports:
                hit = kind.probe(ProbeTarget("modbus-tcp", params, timeout_s))
                if hit:
                    break
        found += hit
        regs = None if hit else _modbus_answers("modbus-tcp", params, timeout_s)
        if regs is not None:
            unknown.append(Unknown("modbus-tcp", params, where, regs))
    for bus in buses:
        say(f"I2C bus {bus}")
        obj = (i2c_objects or {}).get(str(bus))
        for kind in KINDS.values():
            if kind.probe is not None and "i2c" in kind.transports:
                found += kind.probe(ProbeTarget("i2c", {"bus": bus}, timeout_s, obj))
    return found, unknown


def table(found: list[Found], unknown: list[Unknown]) -> str:
    """What answered, one row per device: port, kind, model, serial; then a ``WARNING`` line
    for each device identified with a caveat (a model code its map does not list)."""
    rows = [("port", "kind", "model", "serial")]
    rows += [(f.where, f.kind, f.model, f.serial or "-") for f in found]
    rows += [(u.where, "?", u.describe(), "-") for u in unknown]
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
             for row in rows]  # fmt: skip
    return "\n".join(lines + [f"WARNING: {f.where}: {f.warning}" for f in found if f.warning])


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    return json.dumps(str(value))


def device_names(found: list[Found]) -> list[str]:
    """``psu1``, ``psu2``, ``load1``, ``mag1`` ...: by the kind's first role, numbered."""
    counts: dict[str, int] = {}
    names = []
    for f in found:
        roles = KINDS[f.kind].roles
        role = next(r for r in NAME_PREFIX if r in roles)
        prefix = NAME_PREFIX[role]
        counts[prefix] = counts.get(prefix, 0) + 1
        names.append(f"{prefix}{counts[prefix]}")
    return names


def _cage_lines(supplies: list[str], relays: list[str], mags: list[str],
                scalars: list[str] | None = None) -> list[str]:  # fmt: skip
    """The ``[cage]`` section of a skeleton, commented out when fewer than three supplies
    answered (keys as declared in :data:`rig.config.CAGE_KEYS`)."""
    cage = [
        "[cage]",
        "# FILL IN: which supply drives which coil axis (supplies found: "
        + (", ".join(supplies) or "none")
        + ").",
        "axes = { "
        + ", ".join(f'{ax} = "{s}"' for ax, s in zip("xyz", supplies, strict=False))
        + " }",
        "# FILL IN: the polarity relay board (omit it when the supplies are bipolar)",
        f'polarity = "{relays[0]}"' if relays else '# polarity = "polarity1"',
        "# FILL IN: the reference magnetometer (a calibrated one, never the DUT). A scan cannot",
        "# tell them apart: uncomment this line and name the reference"
        + (f" ({' or '.join(mags)} answered)." if mags else "."),
        f'# reference = "{mags[0] if mags else "mag1"}"',
        *(
            [f'scalar = "{scalars[0]}"   # the total-field sensor (the coil_scalar step)']
            if scalars
            else []
        ),
        'calibration = "cage-calibration.json"   # written by `rig cage characterize`',
        "# FILL IN: the limits of your coils and supplies (these are conservative placeholders)",
        "max_current_a = [1.0, 1.0, 1.0]",
        "max_field_ut = 100.0",
        "max_slew_a_per_s = 1.0",
        "compliance_v = 12.0",
        "# FILL IN: the coils' nameplate constants (uT/A) until the cage is characterized",
        "nominal_k_ut_per_a = [[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, 40.0]]",
        "",
    ]
    if len(supplies) >= 3:
        return cage
    return [
        "# No cage section: fewer than three supplies answered. When the coil supplies are",
        "# connected, scan again or write it by hand:",
        *(f"# {ln}" if ln and not ln.startswith("#") else ln for ln in cage),
    ]


def _found_lines(name: str, f: Found) -> list[str]:
    """The ``[devices.NAME]`` table of a device that answered, with the keys to fill in."""
    lines = [
        f"[devices.{name}]   # {f.model}"
        + (f", serial {f.serial}" if f.serial else "")
        + f" at {f.where}",
        *([f"# WARNING: {f.warning}"] if f.warning else []),
        f'kind = "{f.kind}"',
        f'protocol = "{f.protocol}"',
    ]
    for key, value in f.params.items():
        lines.append(
            f"address = 0x{int(value):02X}" if key == "address" else f"{key} = {_value(value)}"
        )
    kind = KINDS[f.kind]
    if kind.is_output and "max_current_a" in {p.name for p in kind.params}:
        lines.append("# max_current_a = 2.0   # FILL IN: the current limit of what it drives (A)")
    if "magnetometer" in kind.roles:
        lines.append("# rate_hz = 20.0        # the rate to sample it at (Hz)")
    return [*lines, ""]


def _unknown_lines(i: int, u: Unknown) -> list[str]:
    """A commented-out ``[devices.modbusN]`` table for a Modbus device no map recognized."""
    return [
        f"# A Modbus device answered at {u.where} but no register map recognized it",
        "# (a relay board has no model register). FILL IN its kind and map, then uncomment:",
        f"# [devices.modbus{i}]",
        '# kind = "regmap-relay"          # or regmap-supply / regmap-eload',
        '# regmap = "waveshare-relay"     # or r421a08-relay, relay-h-bridge, a file',
        f'# protocol = "{u.protocol}"',
        *(f"# {k} = {_value(v)}" for k, v in u.params.items()),
        "",
    ]


def skeleton(found: list[Found], unknown: Iterable[Unknown] = ()) -> str:
    """A rig configuration (TOML) for what answered; it loads as is, and the cage section says
    what the user must check and fill in."""
    names = device_names(found)

    def named(role: str) -> list[str]:
        return [n for n, f in zip(names, found, strict=True) if role in KINDS[f.kind].roles]

    stamp = time.strftime("%Y-%m-%d %H:%M")
    lines = [
        f"# Rig configuration written by `rig devices scan` on {stamp}.",
        "# The devices below answered; check the names and which one does what.",
        "",
        *_cage_lines(named("supply"), named("relay"), named("magnetometer"), named("scalar")),
    ]
    for name, f in zip(names, found, strict=True):
        lines += _found_lines(name, f)
    for i, u in enumerate(unknown, 1):
        lines += _unknown_lines(i, u)
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``rig devices scan``."""
    parser.add_argument("--port", action="append", default=[], metavar="PATH",
                        help="a serial port to probe besides the listed ones (repeatable)")  # fmt: skip
    parser.add_argument("--i2c-bus", action="append", type=int, default=[], metavar="N",
                        help="an I2C bus /dev/i2c-N to probe besides the listed ones (repeatable)")  # fmt: skip
    parser.add_argument("--tcp", action="append", default=[], metavar="HOST:PORT",
                        help="a Modbus TCP device (or serial gateway) to probe (repeatable)")  # fmt: skip
    parser.add_argument("--only-given", action="store_true",
                        help="probe only the ports and buses given, not every one the system lists")  # fmt: skip
    parser.add_argument("--timeout", type=float, default=0.2, metavar="S",
                        help="reply timeout per probe (s, default 0.2)")  # fmt: skip
    parser.add_argument("--write", type=Path, metavar="FILE",
                        help="write a rig configuration skeleton (TOML) for what answered")  # fmt: skip


def _refuse_existing(path: Path) -> None:
    """Refuse (one line) a ``--write`` file that exists, or a link or non-regular file there."""
    try:
        check_output(path, exclusive=True)
    except FileExistsError:
        raise UserInputError(
            f"{path}: exists; choose a new file name (it is not overwritten)"
        ) from None


def run(args: argparse.Namespace) -> int:
    """Scan, print the table, optionally write the skeleton. 0 when something answered."""
    listed = not args.only_given
    tcp = [parse_tcp(t) for t in args.tcp]
    if args.write is not None:  # a file or a planted link there: refused before the scan
        _refuse_existing(args.write)
    ports = serial_ports(args.port, listed=listed)
    buses: list[int | str] = list(i2c_buses(args.i2c_bus, listed=listed))
    if not (ports or buses or tcp):
        print("rig devices scan: no serial port, I2C bus or TCP address to probe; give --port,"
              " --i2c-bus or --tcp", file=sys.stderr)  # fmt: skip
        return 1

    def progress(message: str) -> None:
        print(f"probing {message} ...", file=sys.stderr)

    found, unknown = scan(ports, buses, tcp, timeout_s=args.timeout, progress=progress)
    print(table(found, unknown))
    if not (found or unknown):
        print("rig devices scan: nothing answered; check power and cables, and give --port or"
              " --tcp for ports this computer does not list", file=sys.stderr)  # fmt: skip
    if args.write is not None:
        try:  # atomically, never through a link, never over a file (issue 51)
            write_output(args.write, (skeleton(found, unknown) + "\n").encode("utf-8"),
                         exclusive=True)  # fmt: skip
        except FileExistsError:
            _refuse_existing(args.write)
        except OSError as exc:
            raise UserInputError(f"cannot write {args.write}: {exc.strerror}: choose another"
                                 " path") from None  # fmt: skip
        load_rig_config(args.write)  # what we write must load
        print(f"wrote {args.write}: check every line marked FILL IN")
    return 0 if found else 1
