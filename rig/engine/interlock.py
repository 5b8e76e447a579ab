"""The interlock: one command at a time drives a rig's outputs.

Each output device (coil supply, polarity relay board, load channel) is known by where it is on
the wire - ``modbus-tcp 10.0.0.5:502 id 1``, ``modbus-rtu /dev/ttyUSB0 id 3`` - not by the name a
rig configuration gives it, so two configurations naming the same supply collide. Host names are
resolved to their numeric addresses (``localhost`` and ``127.0.0.1`` are one supply; a name with
several addresses locks each) and serial paths to the port they point to. A command that drives
outputs takes an exclusive ``flock`` on one lock file per output device; a second command that
would drive any of the same devices refuses in one line naming the holder (its command, PID and
start time). The kernel drops a lock when the last descriptor on it closes, so a holder killed
with SIGKILL never leaves a stale lock; the guardian inherits the descriptors and keeps the rig
locked until it has switched the outputs off.

The locks live in ``$RIG_LOCK_DIR`` (default ``/tmp/rig-locks``) and bind the processes of one
computer: two computers driving the same networked supply are not stopped by it. The folder and
the lock files are trusted only as :mod:`rig.engine.lock_folder` says. In simulated time the
outputs are private to the process, and so are their locks (:mod:`rig.engine.sim_interlock`).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import fcntl
import hashlib
import json
import os
import stat
import sys
import time
from typing import Any

import timebase
from rig import host_identity
from rig.child_process import process_alive
from rig.config import RigConfig
from rig.engine import sim_interlock
from rig.engine.lock_folder import LOCK_DIR_ENV as LOCK_DIR_ENV
from rig.engine.lock_folder import SHARED_SETUP as SHARED_SETUP
from rig.engine.lock_folder import LockFolderError as LockFolderError
from rig.engine.lock_folder import folder_problem as folder_problem
from rig.engine.lock_folder import lock_dir as lock_dir
from rig.engine.lock_folder import open_lock
from rig.engine.lock_folder import open_lock_dir as open_lock_dir
from rig.errors import RigError
from rig.wire_address import lock_addresses as lock_addresses
from rig.wire_address import numeric_hosts as numeric_hosts
from rig.wire_address import output_devices as output_devices
from rig.wire_address import refuse_shared_addresses
from rig.wire_address import wire_address as wire_address
from rig.wire_address import wire_link as wire_link

GUARDIAN_FINISH_S = 15.0
"""How long a new command waits for the guardian of a holder that died to finish switching the
outputs off (s): a few Modbus transactions per device and the coils' decay before the relays.
Another process's guardian: waited for on the wall clock, whatever clock this process runs on."""


class RigBusyError(RigError):
    """Another command holds one of the outputs this command would drive."""


class RigLock:
    """Exclusive hold of a rig's outputs for one command; ``release()`` (or leaving the ``with``
    block) lets the next one in. ``fds`` are the lock descriptors, for a child (the guardian) that
    must keep the rig locked after this process has gone (none in simulated time, whose locks are
    the process's own: :mod:`rig.engine.sim_interlock`)."""

    def __init__(self, cfg: RigConfig, command: str) -> None:
        self.cfg = cfg
        self.command = command
        self.fds: list[int] = []
        self._simulated: tuple[Any, list[str]] | None = None  # (its clock, the addresses held)

    @property
    def held(self) -> bool:
        """Whether the outputs are held (by lock files, or in simulated time by the process)."""
        return bool(self.fds) or self._simulated is not None

    def __enter__(self) -> RigLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def acquire(self) -> None:
        """Lock every output device, in a fixed order (two commands cannot deadlock), or raise
        :class:`RigBusyError` naming the holder (:class:`LockFolderError` for a lock folder that
        cannot be used) and hold nothing. A configuration naming one instrument twice is refused
        first (UserInputError): a second name would drive it without the first one's limits."""
        refuse_shared_addresses(self.cfg)
        names: dict[str, str] = {}  # one lock per address, named after the first device on it
        for name, addresses in sorted(output_devices(self.cfg).items(), reverse=True):
            names.update(dict.fromkeys(addresses, name))
        if timebase.is_simulated():
            self._take_simulated(names)
            return
        dir_fd = open_lock_dir()
        assert dir_fd is not None  # created when missing
        folder = lock_dir()
        # read by other processes: the wall clock's date, whatever clock this one runs on
        holder = json.dumps({"command": self.command, "pid": os.getpid(),
                             "since": dt.datetime.now().astimezone().isoformat(timespec="seconds"),
                             "process": host_identity.identity()})  # fmt: skip
        try:
            for address, name in sorted(names.items()):
                fd = open_lock(dir_fd, folder, _lock_name(address))
                try:
                    _flock_or_wait_for_guardian(fd)
                except OSError as exc:
                    if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                        os.close(fd)
                        raise
                    other = _holder(fd)
                    os.close(fd)
                    raise self._busy(name, address, other) from None
                with contextlib.suppress(OSError):  # another account's file: locked, unnamed
                    os.ftruncate(fd, 0)
                    os.pwrite(fd, holder.encode(), 0)
                self.fds.append(fd)
        except BaseException:
            self.release()
            raise
        finally:
            os.close(dir_fd)

    def _busy(self, name: str, address: str, other: str) -> RigBusyError:
        return RigBusyError(
            f"{self.cfg.path}: {name} ({address}) is in use by {other}; wait for it to finish or"
            " stop it first (Ctrl-C in its terminal, or kill the PID)"
        )

    def _take_simulated(self, names: dict[str, str]) -> None:
        """:meth:`acquire` in simulated time: held in this process, per simulated clock."""
        clock = timebase.current()
        taken = sim_interlock.take(clock, names, self.command)
        if isinstance(taken, tuple):
            raise self._busy(*taken)
        self._simulated = (clock, taken)

    def release(self) -> None:
        """Let go of every lock (the files stay: removing one would race with a new holder)."""
        if self._simulated is not None:
            sim_interlock.give_back(*self._simulated)
            self._simulated = None
        for fd in self.fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self.fds = []


def holders(cfg: RigConfig) -> dict[str, str]:
    """Output devices of ``cfg`` held by a command right now: name -> who (for ``rig safe``, so
    it never raises: a lock folder it cannot trust or open reports nothing). In simulated time,
    the holders on this process's simulated clock."""
    if timebase.is_simulated():
        return sim_interlock.holders(timebase.current(), output_devices(cfg))
    try:
        dir_fd = open_lock_dir(create=False)
    except LockFolderError:
        return {}
    if dir_fd is None:
        return {}
    found = {}
    flags = os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK | os.O_NOCTTY
    try:
        for name, addresses in output_devices(cfg).items():
            for address in addresses:
                try:
                    fd = os.open(_lock_name(address), flags, dir_fd=dir_fd)
                except OSError:
                    continue
                try:
                    if not stat.S_ISREG(os.fstat(fd).st_mode):
                        continue
                    try:
                        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
                    except OSError:
                        found[name] = _holder(fd)
                finally:
                    os.close(fd)
    finally:
        os.close(dir_fd)
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
            if pid is None or _holder_alive(fd, pid) or time.monotonic() > deadline:
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


def _holder_alive(fd: int, pid: int) -> bool:
    """Is the holder still running? Yes when it cannot be told: a holder in another PID
    namespace (a container) or of another boot is judged alive, never waited out."""
    process = (_record(fd) or {}).get("process")
    if process is None:  # a record of an older version
        return process_alive(pid)
    return host_identity.alive(process) is not False


def _holder_pid(fd: int) -> int | None:
    pid = (_record(fd) or {}).get("pid")
    return pid if isinstance(pid, int) and pid > 0 else None


def _lock_name(address: str) -> str:
    """The lock file of a wire address, in the lock folder."""
    return hashlib.sha256(address.encode()).hexdigest()[:20] + ".lock"


def _holder(fd: int) -> str:
    """Who holds a lock, as its holder wrote it: "'rig run X' (PID 123, since 14:02:11)"."""
    info = _record(fd)
    if info is None:
        return "another command (its record is unreadable)"
    since = str(info.get("since", "?"))
    return f"'{info.get('command', '?')}' (PID {info.get('pid', '?')}, since {since})"
