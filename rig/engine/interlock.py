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
computer: two computers driving the same networked supply are not stopped by it. The folder is
trusted only when nobody else can plant files in it (docs/reliability.md, "The lock folder"):

* it is a real folder (not a symbolic link), owned by you or by root;
* nobody outside its owner and group can write to it (no world write, so not a 1777 folder like
  /tmp), and when its group may write, you belong to that group or own the folder.

A missing folder is created private (0700, yours). A lab where several accounts share a rig has
root create it once for a group of those accounts, with the group inherited by the lock files::

    sudo install -d -o root -g rig -m 2770 /var/lib/rig-locks   # then RIG_LOCK_DIR=/var/lib/rig-locks

Lock files are opened relative to the folder's descriptor with ``O_NOFOLLOW`` and must be regular
files with one link, owned by you or root, or (in a group folder) by its group; they are created
0600 in a private folder and 0660 in a group folder. Anything else is refused in one line naming
the fix, before a byte is written; a command that cannot use the folder (another user's private
folder) is refused the same way (exit 2).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import fcntl
import grp
import hashlib
import json
import os
import pwd
import stat
import sys
import tempfile
import time
from pathlib import Path

from rig import host_identity
from rig.child_process import process_alive
from rig.config import RigConfig
from rig.errors import RigError
from rig.wire_address import lock_addresses as lock_addresses
from rig.wire_address import numeric_hosts as numeric_hosts
from rig.wire_address import output_devices as output_devices
from rig.wire_address import refuse_shared_addresses
from rig.wire_address import wire_address as wire_address
from rig.wire_address import wire_link as wire_link

LOCK_DIR_ENV = "RIG_LOCK_DIR"
"""Environment variable naming the folder of the lock files (shared by every user of the rig)."""


GUARDIAN_FINISH_S = 15.0
"""How long a new command waits for the guardian of a holder that died to finish switching the
outputs off (s): a few Modbus transactions per device and the coils' decay before the relays."""

SHARED_SETUP = "sudo install -d -o root -g GROUP -m 2770 {folder}"
"""How root makes a lock folder for the accounts of GROUP (docs/reliability.md, "The lock folder")."""


class RigBusyError(RigError):
    """Another command holds one of the outputs this command would drive."""


class LockFolderError(RigError):
    """The lock folder or a lock file in it cannot be trusted or used (exit 2, one line)."""


def lock_dir() -> Path:
    """The folder of the lock files: ``$RIG_LOCK_DIR``, else ``/tmp/rig-locks``."""
    return Path(os.environ.get(LOCK_DIR_ENV) or Path(tempfile.gettempdir()) / "rig-locks")


def _user(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return f"uid {uid}"


def _group(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


def _in_group(gid: int) -> bool:
    return gid == os.getegid() or gid in os.getgroups()


def _see_docs(folder: Path) -> str:
    return (
        f"or have root make a folder for the accounts that share the rig"
        f" ({SHARED_SETUP.format(folder=folder)}; docs/reliability.md, 'The lock folder')"
    )


def folder_problem(folder: Path, st: os.stat_result) -> str | None:
    """Why the lock folder ``folder`` (its ``lstat``) cannot be trusted, as a clause ending with
    the fix; None when it can (see the module's rules)."""
    me = os.geteuid()
    if stat.S_ISLNK(st.st_mode):
        return (
            f"is a symbolic link (of {_user(st.st_uid)}), which could lead anywhere: remove it,"
            f" or set {LOCK_DIR_ENV} to the folder itself"
        )
    if not stat.S_ISDIR(st.st_mode):
        return f"is not a folder: remove it, or set {LOCK_DIR_ENV} to another folder"
    mode = f"mode {stat.S_IMODE(st.st_mode):o}"
    if st.st_uid not in (me, 0):
        return (
            f"belongs to {_user(st.st_uid)}, who could replace the lock files: only you or root"
            f" may own the lock folder; have {_user(st.st_uid)} remove it {_see_docs(folder)}"
        )
    if st.st_mode & stat.S_IWOTH:
        return (
            f"anyone may write to it ({mode}) and plant links or files there: make it private"
            f" (chmod 0700 {folder}) {_see_docs(folder)}"
        )
    if st.st_mode & stat.S_IWGRP and st.st_uid != me and not _in_group(st.st_gid):
        return (
            f"group {_group(st.st_gid)} may write to it ({mode}) and you are not in that group:"
            f" ask to be added to {_group(st.st_gid)}, or have its owner remove the group's write"
            f" permission"
        )
    return None


def open_lock_dir(create: bool = True) -> int | None:
    """A descriptor of the checked lock folder (created private, 0700, when missing and
    ``create``); None when it is missing and not ``create``. Raises :class:`LockFolderError`
    (one line with the fix) for a folder that cannot be trusted or used."""
    folder = lock_dir()
    if create and not os.path.lexists(folder):
        try:
            folder.parent.mkdir(parents=True, exist_ok=True)
            os.mkdir(folder, 0o700)
        except FileExistsError:
            pass  # another command made it first: checked below like any folder
        except OSError as exc:
            raise LockFolderError(
                f"cannot create the lock folder {folder} ({exc.strerror}): set {LOCK_DIR_ENV} to"
                f" a folder you may create, {_see_docs(folder)}"
            ) from None
    try:
        before = os.lstat(folder)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise LockFolderError(f"{LOCK_DIR_ENV} {folder}: cannot read it ({exc.strerror})") from None
    problem = folder_problem(folder, before)
    if problem is not None:
        raise LockFolderError(f"lock folder {folder} ({LOCK_DIR_ENV}) {problem}")
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        raise LockFolderError(_not_usable(folder, before, exc)) from None
    st = os.fstat(fd)
    if (st.st_dev, st.st_ino) != (before.st_dev, before.st_ino):  # replaced meanwhile
        os.close(fd)
        raise LockFolderError(
            f"lock folder {folder} ({LOCK_DIR_ENV}) was replaced while it was checked; run again"
        )
    return fd


def _not_usable(folder: Path, st: os.stat_result, exc: OSError) -> str:
    """The one line for a trusted lock folder this account may not use."""
    if exc.errno in (errno.EACCES, errno.EPERM):
        return (
            f"lock folder {folder} ({LOCK_DIR_ENV}) belongs to {_user(st.st_uid)} (group"
            f" {_group(st.st_gid)}, mode {stat.S_IMODE(st.st_mode):o}) and is not shared with"
            f" you, so you cannot take the rig's locks: have root share it with a group you are"
            f" in (chgrp GROUP {folder}; chmod 2770 {folder}; docs/reliability.md, 'The lock"
            f" folder')"
        )
    return f"lock folder {folder} ({LOCK_DIR_ENV}): cannot open it ({exc.strerror})"


def _open_lock(dir_fd: int, folder: Path, name: str) -> int:
    """The lock file ``name`` in the folder of ``dir_fd``, opened without following a link and
    created when missing (0600, or 0660 in a folder its group may write); refused unless it is a
    regular file with one link owned by you, root or (in a group folder) the folder's group."""
    dir_st = os.fstat(dir_fd)
    group_folder = bool(dir_st.st_mode & stat.S_IWGRP)
    flags = os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK | os.O_NOCTTY
    path = folder / name
    try:
        try:
            fd = os.open(name, os.O_RDWR | os.O_CREAT | os.O_EXCL | flags, 0o600, dir_fd=dir_fd)
            os.fchmod(fd, 0o660 if group_folder else 0o600)  # whatever the umask
        except FileExistsError:
            try:
                fd = os.open(name, os.O_RDWR | flags, dir_fd=dir_fd)
            except PermissionError:  # another account's file: a lock needs no write
                fd = os.open(name, os.O_RDONLY | flags, dir_fd=dir_fd)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise LockFolderError(
                f"lock file {path} is a symbolic link, which the rig never makes: someone planted"
                f" it; remove it and check who may write to {folder}"
            ) from None
        if exc.errno in (errno.EACCES, errno.EPERM):
            raise LockFolderError(_not_usable(folder, dir_st, exc)) from None
        if exc.errno == errno.EISDIR:
            raise LockFolderError(
                f"lock file {path} is not a regular file, which the rig never makes: remove it"
                f" and check who may write to {folder}"
            ) from None
        raise LockFolderError(f"lock file {path}: cannot open it ({exc.strerror})") from None
    st = os.fstat(fd)
    problem = None
    if not stat.S_ISREG(st.st_mode):
        problem = "is not a regular file"
    elif st.st_nlink != 1:
        problem = f"has {st.st_nlink} links (a hard link to another file?)"
    elif st.st_uid not in (os.geteuid(), 0) and not (group_folder and st.st_gid == dir_st.st_gid):
        problem = f"belongs to {_user(st.st_uid)} (group {_group(st.st_gid)})"
    if problem is not None:
        os.close(fd)
        raise LockFolderError(
            f"lock file {path} {problem}, which the rig never makes: remove it and check who may"
            f" write to {folder}"
        )
    return fd


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
        :class:`RigBusyError` naming the holder (:class:`LockFolderError` for a lock folder that
        cannot be used) and hold nothing. A configuration naming one instrument twice is refused
        first (UserInputError): a second name would drive it without the first one's limits."""
        refuse_shared_addresses(self.cfg)
        dir_fd = open_lock_dir()
        assert dir_fd is not None  # created when missing
        folder = lock_dir()
        holder = json.dumps({"command": self.command, "pid": os.getpid(),
                             "since": dt.datetime.now().astimezone().isoformat(timespec="seconds"),
                             "process": host_identity.identity()})  # fmt: skip
        names: dict[str, str] = {}  # one lock per address, named after the first device on it
        for name, addresses in sorted(output_devices(self.cfg).items(), reverse=True):
            names.update(dict.fromkeys(addresses, name))
        try:
            for address, name in sorted(names.items()):
                fd = _open_lock(dir_fd, folder, _lock_name(address))
                try:
                    _flock_or_wait_for_guardian(fd)
                except OSError as exc:
                    if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                        os.close(fd)
                        raise
                    other = _holder(fd)
                    os.close(fd)
                    raise RigBusyError(
                        f"{self.cfg.path}: {name} ({address}) is in use by {other}; wait for it"
                        " to finish or stop it first (Ctrl-C in its terminal, or kill the PID)"
                    ) from None
                with contextlib.suppress(OSError):  # another account's file: locked, unnamed
                    os.ftruncate(fd, 0)
                    os.pwrite(fd, holder.encode(), 0)
                self.fds.append(fd)
        except BaseException:
            self.release()
            raise
        finally:
            os.close(dir_fd)

    def release(self) -> None:
        """Let go of every lock (the files stay: removing one would race with a new holder)."""
        for fd in self.fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self.fds = []


def holders(cfg: RigConfig) -> dict[str, str]:
    """Output devices of ``cfg`` held by a command right now: name -> who (for ``rig safe``, so
    it never raises: a lock folder it cannot trust or open reports nothing)."""
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
