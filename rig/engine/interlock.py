"""The interlock: one command at a time drives a rig's outputs.

Each output device (coil supply, polarity relay board, load channel) is known by where it is on
the wire - ``modbus-tcp 10.0.0.5:502 id 1``, ``modbus-rtu /dev/ttyUSB0 id 3`` - not by the name a
rig configuration gives it, so two configurations naming the same supply collide. A command that
drives outputs takes an exclusive ``flock`` on one lock file per output device; a second command
that would drive any of the same devices refuses in one line naming the holder (its command, PID
and start time). The kernel drops a lock when the last descriptor on it closes, so a holder killed
with SIGKILL never leaves a stale lock; the guardian inherits the descriptors and keeps the rig
locked until it has switched the outputs off.

The locks live in ``$RIG_LOCK_DIR`` (default ``/tmp/rig-locks``) and bind the processes of one
computer: two computers driving the same networked supply are not stopped by it.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import fcntl
import hashlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from drivers.registry import output_kinds
from rig.child_process import process_alive
from rig.config import DeviceConfig, RigConfig
from rig.errors import RigError

LOCK_DIR_ENV = "RIG_LOCK_DIR"
"""Environment variable naming the folder of the lock files (shared by every user of the rig)."""


GUARDIAN_FINISH_S = 15.0
"""How long a new command waits for the guardian of a holder that died to finish switching the
outputs off (s): a few Modbus transactions per device and the coils' decay before the relays."""


class RigBusyError(RigError):
    """Another command holds one of the outputs this command would drive."""


def lock_dir() -> Path:
    """The folder of the lock files (created world-writable and sticky, like /tmp)."""
    folder = Path(os.environ.get(LOCK_DIR_ENV) or Path(tempfile.gettempdir()) / "rig-locks")
    if not folder.is_dir():
        folder.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(OSError):  # another user's folder: theirs to set
            folder.chmod(0o1777)
    return folder


def wire_link(dev: DeviceConfig) -> str:
    """The wire a device is on (a TCP endpoint, a serial port, an I2C bus), the same for every
    configuration that names it: devices on one link take turns on it."""
    if dev.protocol == "modbus-tcp":
        return f"modbus-tcp {dev.get('host')}:{dev.get('port', 502)}"
    if dev.protocol == "modbus-rtu":
        path = str(dev.get("path"))
        if "://" not in path:
            path = os.path.realpath(path)  # /dev/serial/by-id/... and /dev/ttyUSB0 are one port
        return f"modbus-rtu {path}"
    if dev.protocol == "i2c":
        return f"i2c bus {dev.get('bus', 1)}"
    return f"{dev.protocol} {os.path.realpath(str(dev.get('path')))}"


def wire_address(dev: DeviceConfig) -> str:
    """Where a device is on the wire, the same for every configuration that names it."""
    if dev.protocol in ("modbus-tcp", "modbus-rtu"):
        return f"{wire_link(dev)} id {dev.get('device_id', 1)}"
    if dev.protocol == "i2c":
        return f"{wire_link(dev)} address {int(dev.get('address')):#04x}"
    return wire_link(dev)


def output_devices(cfg: RigConfig) -> dict[str, str]:
    """The output devices of ``cfg`` (name -> wire address): what the interlock locks."""
    kinds = output_kinds()
    return {name: wire_address(d) for name, d in cfg.devices.items() if d.kind in kinds}


class RigLock:
    """Exclusive hold of a rig's outputs for one command; ``release()`` (or leaving the ``with``
    block) lets the next one in. ``fds`` are the lock descriptors, for a child (the guardian) that
    must keep the rig locked after this process has gone."""

    def __init__(self, cfg: RigConfig, command: str) -> None:
        self.cfg = cfg
        self.command = command
        self.fds: list[int] = []

    def __enter__(self) -> RigLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def acquire(self) -> None:
        """Lock every output device, in a fixed order (two commands cannot deadlock), or raise
        :class:`RigBusyError` naming the holder and hold nothing."""
        folder = lock_dir()
        holder = json.dumps({"command": self.command, "pid": os.getpid(),
                             "since": dt.datetime.now().astimezone().isoformat(timespec="seconds")})  # fmt: skip
        devices = output_devices(self.cfg)
        names = {a: n for n, a in sorted(devices.items(), reverse=True)}  # one lock per address
        for address, name in sorted(names.items()):
            fd = os.open(_lock_path(folder, address), os.O_RDWR | os.O_CREAT, 0o666)
            try:
                _flock_or_wait_for_guardian(fd)
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                    os.close(fd)
                    raise
                other = _holder(fd)
                os.close(fd)
                self.release()
                raise RigBusyError(
                    f"{self.cfg.path}: {name} ({address}) is in use by {other}; wait for it to"
                    " finish or stop it first (Ctrl-C in its terminal, or kill the PID)"
                ) from None
            with contextlib.suppress(OSError):  # read-only lock folder: locked, just unnamed
                os.ftruncate(fd, 0)
                os.pwrite(fd, holder.encode(), 0)
            self.fds.append(fd)

    def release(self) -> None:
        """Let go of every lock (the files stay: removing one would race with a new holder)."""
        for fd in self.fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self.fds = []


def holders(cfg: RigConfig) -> dict[str, str]:
    """Output devices of ``cfg`` held by a command right now: name -> who (for ``rig safe``)."""
    folder = lock_dir()
    found = {}
    for name, address in output_devices(cfg).items():
        path = _lock_path(folder, address)
        if not path.exists():
            continue
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except OSError:
                found[name] = _holder(fd)
        finally:
            os.close(fd)
    return found


def _flock_or_wait_for_guardian(fd: int) -> None:
    """Take the lock; if its holder has died, its guardian still holds it while it switches the
    outputs off: wait up to :data:`GUARDIAN_FINISH_S` for that, then give up like a live holder.
    Raises OSError (EWOULDBLOCK) when the lock stays held."""
    deadline = time.monotonic() + GUARDIAN_FINISH_S
    told = False
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise
            pid = _holder_pid(fd)
            if pid is None or process_alive(pid) or time.monotonic() > deadline:
                raise
            if not told:
                print(f"rig: PID {pid} has died; waiting for its guardian to switch the outputs"
                      " off", file=sys.stderr)  # fmt: skip
                told = True
            time.sleep(0.1)


def _record(fd: int) -> dict[str, object] | None:
    """The holder's record in a lock file (None when unreadable)."""
    try:
        info = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) else None


def _holder_pid(fd: int) -> int | None:
    pid = (_record(fd) or {}).get("pid")
    return pid if isinstance(pid, int) and pid > 0 else None


def _lock_path(folder: Path, address: str) -> Path:
    return folder / (hashlib.sha256(address.encode()).hexdigest()[:20] + ".lock")


def _holder(fd: int) -> str:
    """Who holds a lock, as its holder wrote it: "'rig run X' (PID 123, since 14:02:11)"."""
    info = _record(fd)
    if info is None:
        return "another command (its record is unreadable)"
    since = str(info.get("since", "?"))
    return f"'{info.get('command', '?')}' (PID {info.get('pid', '?')}, since {since})"
