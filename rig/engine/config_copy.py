"""The last configuration a run used, kept per rig file: what ``rig safe`` switches off when the
file itself can no longer be parsed (a syntax typo, a nesting too deep for the parser).

Each session (:class:`rig.engine.session.RigSession`) keeps the raw text of the configuration
it drives, once it holds the interlock, in the interlock's lock folder
(:func:`rig.engine.interlock.lock_dir`: checked private, or shared only with the rig's group),
as ``config-<sha256 of the file's resolved path>.toml``. Copies are written and read as the lock
files are: relative to the checked folder, never through a link, replaced atomically. None is kept
in simulated time (:mod:`timebase`): its outputs are simulated inside the process, out of reach of
``rig safe``, and a copy would stand for a real rig file at that path.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import os
import stat
import tomllib
from pathlib import Path
from typing import Any

import timebase
from rig.engine.interlock import LockFolderError, lock_dir, open_lock_dir


def copy_name(path: Path) -> str:
    """The copy's file name in the lock folder for the rig file ``path``."""
    resolved = str(Path(path).resolve())
    return f"config-{hashlib.sha256(resolved.encode()).hexdigest()[:20]}.toml"


def keep_config_copy(path: Path, raw: dict[str, Any]) -> bool:
    """Keep the text of the rig file ``path`` as the last configuration a run used, if it still
    says what was parsed (``raw``: its devices as the session has them); False when it was not
    kept (the file changed since, or the lock folder cannot be used: the previous copy stays;
    simulated time)."""
    if timebase.is_simulated():
        return False
    try:
        text = Path(path).read_text(encoding="utf-8")
        if tomllib.loads(text).get("devices") != raw.get("devices"):
            return False
        dir_fd = open_lock_dir()
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, RecursionError, LockFolderError):
        return False
    if dir_fd is None:
        return False
    name = copy_name(path)
    tmp = f".{name}.{os.getpid()}.tmp"
    group = bool(os.fstat(dir_fd).st_mode & stat.S_IWGRP)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                     0o600, dir_fd=dir_fd)  # fmt: skip
        try:
            os.fchmod(fd, 0o660 if group else 0o600)
            os.write(fd, text.encode("utf-8"))
        finally:
            os.close(fd)
        os.replace(tmp, name, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
        return True
    except OSError:
        with contextlib.suppress(OSError):
            os.unlink(tmp, dir_fd=dir_fd)
        return False
    finally:
        os.close(dir_fd)


def last_config_copy(path: Path) -> tuple[str, str] | None:
    """The last configuration a run used from the rig file ``path``: (its text, where it is and
    when it was kept, for people), or None when there is none that can be trusted (a link, a
    file of another account, or no lock folder)."""
    try:
        dir_fd = open_lock_dir(create=False)
    except LockFolderError:
        return None
    if dir_fd is None:
        return None
    name = copy_name(path)
    try:
        dir_st = os.fstat(dir_fd)
        fd = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK,
                     dir_fd=dir_fd)  # fmt: skip
    except OSError:
        return None
    finally:
        os.close(dir_fd)
    try:
        st = os.fstat(fd)
        mine = st.st_uid in (os.geteuid(), 0) or (
            bool(dir_st.st_mode & stat.S_IWGRP) and st.st_gid == dir_st.st_gid
        )
        if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1 or not mine:
            return None
        with os.fdopen(os.dup(fd), "rb") as f:
            text = f.read().decode("utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    finally:
        os.close(fd)
    when = dt.datetime.fromtimestamp(st.st_mtime).astimezone().isoformat(timespec="seconds")
    return text, f"{lock_dir() / name}, {when}"
