"""The interlock's lock folder (``$RIG_LOCK_DIR``, default ``/tmp/rig-locks``) and its lock files:
checked before a byte is written (:mod:`rig.engine.interlock` takes its locks there).

The folder is trusted only when nobody else can plant files in it (docs/reliability.md, "The lock folder"):

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

import errno
import grp
import os
import pwd
import stat
import tempfile
from pathlib import Path

from rig.errors import RigError

LOCK_DIR_ENV = "RIG_LOCK_DIR"
"""Environment variable naming the folder of the lock files (shared by every user of the rig)."""

SHARED_SETUP = "sudo install -d -o root -g GROUP -m 2770 {folder}"
"""How root makes a lock folder for the accounts of GROUP (docs/reliability.md, "The lock folder")."""


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


def open_lock(dir_fd: int, folder: Path, name: str) -> int:
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
