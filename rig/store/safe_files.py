"""Run-folder files read and written without following symbolic links.

A run folder may sit in a folder other accounts can write to, and it is served by the web page,
exported and reported on by whoever asks. A link planted in it (``plot.png -> /etc/shadow``,
``run.h5 -> ~/.bashrc``) must never make the rig read or overwrite a file outside the folder, so
every run-folder file goes through this module:

* reads open with ``O_NOFOLLOW`` and accept only regular files (no link, FIFO or device);
* writes go to a new temporary file beside the target (``O_CREAT | O_EXCL | O_NOFOLLOW``) that
  then replaces the target by ``rename``, which replaces a link itself, never what it points to;
* a run folder that is itself a link, or not a folder, is refused.

Output files a user names on the command line go through :mod:`rig.io.output_files` instead.

Every refusal is an :class:`UnsafeFileError` (a ``RigError``: one line, exit 2) naming the file.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

from rig.errors import RigError

READ_FLAGS = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
"""A FIFO opened non-blocking does not hang the reader; the type check then refuses it."""


class UnsafeFileError(RigError):
    """A run-folder path is a symbolic link or not a regular file (folder)."""


def _refuse(path: Path, what: str) -> UnsafeFileError:
    return UnsafeFileError(
        f"{path}: {what}; the rig reads and writes only regular files in a run folder (remove it)"
    )


def check_folder(folder: Path) -> Path:
    """``folder`` itself, after checking it is a real folder and not a link to one."""
    try:
        st = os.lstat(folder)
    except FileNotFoundError:
        raise UnsafeFileError(f"{folder}: no such run folder") from None
    if stat.S_ISLNK(st.st_mode):
        raise _refuse(folder, "is a symbolic link")
    if not stat.S_ISDIR(st.st_mode):
        raise _refuse(folder, "is not a folder")
    return folder


def regular_file(path: Path) -> Path:
    """``path`` after checking it is a regular file and not a link (FileNotFoundError if it is
    missing). For libraries that open by name (SQLite, h5py); prefer :func:`read_bytes`."""
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode):
        raise _refuse(path, "is a symbolic link")
    if not stat.S_ISREG(st.st_mode):
        raise _refuse(path, "is not a regular file")
    return path


def is_regular_file(path: Path) -> bool:
    """True for an existing regular file that is not a link (never raises)."""
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:
        return False


def open_fd(path: Path) -> int:
    """A read-only descriptor on the regular file ``path``, never through a link (the caller
    closes it). FileNotFoundError if missing."""
    try:
        fd = os.open(path, READ_FLAGS)
    except OSError as exc:
        if exc.errno == 40:  # ELOOP: the last component is a symbolic link
            raise _refuse(path, "is a symbolic link") from None
        raise
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise _refuse(path, "is not a regular file")
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_bytes(path: Path, max_bytes: int | None = None) -> bytes:
    """The content of the regular file ``path`` (never through a link). ``max_bytes``: refuse a
    larger file (UnsafeFileError) rather than read it all."""
    fd = open_fd(path)
    with os.fdopen(fd, "rb") as fh:
        if max_bytes is not None and os.fstat(fh.fileno()).st_size > max_bytes:
            raise UnsafeFileError(f"{path}: larger than {max_bytes} bytes; not read")
        return fh.read()


def read_text(path: Path, max_bytes: int | None = None) -> str:
    """:func:`read_bytes` decoded as UTF-8."""
    return read_bytes(path, max_bytes).decode("utf-8")


@contextlib.contextmanager
def replacing(path: Path, mode: int = 0o644) -> Iterator[Path]:
    """A new, empty temporary file beside ``path`` (permissions ``mode``, umask aside) for the
    caller to write by name; on leaving the block without an error it replaces ``path`` (a link
    there is replaced, its target left alone), else it is removed. The folder holding ``path``
    must not be a link."""
    parent = check_folder(path.parent)
    tmp = parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    try:
        os.fchmod(fd, mode & ~_umask())
    finally:
        os.close(fd)
    try:
        yield tmp
        if os.path.isdir(path) and not os.path.islink(path):
            raise _refuse(path, "is a folder")
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def writing(path: Path, mode: int = 0o644, *, newline: str | None = None) -> Iterator[TextIO]:
    """A text file (UTF-8) to write in pieces; on leaving the block without an error it replaces
    ``path`` as :func:`replacing` does (a link there is replaced, its target left alone)."""
    with replacing(path, mode) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        with os.fdopen(fd, "w", encoding="utf-8", newline=newline) as fh:
            yield fh


def write_bytes(path: Path, data: bytes, mode: int = 0o644) -> None:
    """Write ``data`` to ``path`` atomically, never through a link (``mode``: its permissions,
    0o600 for a file only its owner may read)."""
    with replacing(path, mode) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)


def write_text(path: Path, text: str, mode: int = 0o644) -> None:
    """:func:`write_bytes` of ``text`` as UTF-8."""
    write_bytes(path, text.encode("utf-8"), mode)


def _umask() -> int:
    """The process's umask (read without changing it where Linux tells it)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    return 0o022
