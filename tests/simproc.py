"""`rig sim` as a child process for tests that drive the rig across process boundaries."""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Generator, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pymodbus.client import ModbusSerialClient, ModbusTcpClient

from rig.child_process import start_child, stop_child


@contextmanager
def sim_process(
    folder: Path, argv: Sequence[str] | None = None, stop_wait_s: float = 15.0
) -> Iterator[tuple[Path, dict[str, Any]]]:
    """Start `rig sim`, yield (rig configuration path, devices of the endpoints file), stop it.

    The child dies with this process (SIGTERM from the kernel on Linux, see rig.child_process)
    even when pytest itself is killed; on the normal path it gets SIGINT, ``stop_wait_s`` (s) to
    stop, then SIGKILL. ``argv`` replaces the command (tests of this helper); it must write both
    files, whose paths are appended as ``--rig-config RIG --endpoints-json EP``.
    """
    rig_toml, ep = folder / "rig.toml", folder / "endpoints.json"
    command = list(argv) if argv is not None else [sys.executable, "-m", "rig.cli", "-q", "sim"]
    proc = start_child([*command, "--rig-config", str(rig_toml), "--endpoints-json", str(ep)])
    try:
        deadline = time.monotonic() + 20
        while not (rig_toml.exists() and ep.exists()):
            assert proc.poll() is None and time.monotonic() < deadline, "rig sim did not start"
            time.sleep(0.05)
        yield rig_toml, json.loads(ep.read_text())["devices"]
    finally:
        stop_child(proc, wait_s=stop_wait_s)


LOAD_INPUT_STATE = 0x0510
LOAD_OFF = (0x0A00, 43)
"""The simulated Maynuo M97xx load (regmaps/maynuo-m97.toml): its input state coil (ISTATE, read by
function 01); CMD register and its input-off command (function 16 only: the M97xx has no
function 06)."""


def output_registers(
    devices: dict[str, Any], tcp_only: bool = False
) -> Generator[tuple[str, Any, int, int], None, None]:
    """(name, connected client, output-state register, device id) of every supply and load, on
    their own wires (RTU ports are exclusive: only ``tcp_only`` ones while a run holds them). The
    Maynuo load's state is the coil 0x0510; it is switched by commands to 0x0A00
    (:data:`LOAD_OFF`)."""
    for name, d in devices.items():
        if d["kind"] not in ("riden-rd60xx", "regmap-eload"):
            continue
        if tcp_only and d["protocol"] != "modbus-tcp":
            continue
        reg = 18 if d["kind"] == "riden-rd60xx" else LOAD_INPUT_STATE
        if d["protocol"] == "modbus-tcp":
            client: Any = ModbusTcpClient(d["host"], port=d["port"], timeout=2)
        else:
            client = ModbusSerialClient(d["path"], baudrate=d["baudrate"], timeout=2)
        with client:
            yield name, client, reg, d["device_id"]


def outputs(devices: dict[str, Any], tcp_only: bool = False) -> dict[str, int]:
    """Output-enable state of every supply and load. Each client is closed before a failed read
    raises: a generator left suspended inside its ``with`` by the consumer's exception would be
    closed only by the garbage collector, which may finalize its socket first (an unclosed
    socket's ResourceWarning)."""
    found: dict[str, int] = {}
    registers = output_registers(devices, tcp_only)
    try:
        for name, client, reg, dev_id in registers:
            if reg == LOAD_INPUT_STATE:
                found[name] = int(client.read_coils(reg, count=1, device_id=dev_id).bits[0])
            else:
                found[name] = client.read_holding_registers(
                    reg, count=1, device_id=dev_id
                ).registers[0]
    finally:
        registers.close()  # the open client's ``with`` ends here, whatever was raised
    return found


def children(pid: int) -> list[int]:
    """The process ids of ``pid``'s children (Linux ``/proc``; none where it does not say)."""
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return []
    kids: list[int] = []
    for tid in tids:
        try:
            kids += [int(c) for c in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()]
        except (OSError, ValueError):
            continue
    return kids
