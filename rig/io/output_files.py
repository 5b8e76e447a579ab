"""Output files a user names on the command line, written without following links (issue 51).

``rig calibrate --out/--c-header/--ardupilot/--px4/--history``, ``rig example-data``, ``rig design
--out`` and ``rig cage hold --csv`` wrote with a plain ``open``, which follows a symbolic link
another account planted at that path (``result.json -> ~/.bashrc``); a dangling link even created
its target. Here a link there, or a file that is not regular (FIFO, folder, device), is refused in
one line (:class:`rig.errors.UserInputError`, exit 2) naming the path and the fix, rather than
replaced: the user named that path and may not know what was put there. The folder holding it may
be a link (the user chose it). The data goes to a new temporary file beside it (``O_CREAT |
O_EXCL | O_NOFOLLOW``) that then replaces it by ``rename``, which never follows a link: a reader
sees the old file or the new one, never half of one.

(Run-folder files have their own rules: :mod:`rig.store.safe_files`. This module imports nothing
heavy: ``rig calibrate`` loads neither sqlite3 nor scipy.)
"""

from __future__ import annotations

import contextlib
import os
import secrets
import stat
from pathlib import Path

from rig.errors import UserInputError


def _refuse_output(path: Path, what: str, fix: str = "choose another file name") -> UserInputError:
    return UserInputError(f"{path}: {what}: {fix}")


def check_output(path: Path, *, exclusive: bool = False) -> os.stat_result | None:
    """What :func:`write_output` refuses, checked before the work that makes the data (a command
    writing several files checks them all first, so a refusal writes none): a symbolic link or a
    file that is not regular (:class:`UserInputError`), with ``exclusive`` any file
    (FileExistsError). Returns the file's status, None when there is none."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    if stat.S_ISLNK(st.st_mode):
        raise _refuse_output(path, "is a symbolic link, which the rig does not write through"
                             " (another account may have planted it)",
                             "remove it or choose another file name")  # fmt: skip
    if not stat.S_ISREG(st.st_mode):
        raise _refuse_output(path, "is not a regular file (a folder, FIFO or device)")
    if exclusive:
        raise FileExistsError(17, "File exists", str(path))
    return st


def write_output(path: Path, data: bytes, *, exclusive: bool = False) -> None:
    """Write ``data`` to the user-named file ``path``: never through a symbolic link on its last
    component (a link, even a dangling one, is refused: :class:`UserInputError`), never into a
    FIFO or device, and atomically (a new temporary file beside it, ``O_CREAT | O_EXCL |
    O_NOFOLLOW``, renamed over it: a reader sees the old file or the new one, never half of one).
    An existing file keeps its permissions; a new one gets 0o644 less the umask. ``exclusive``:
    refuse an existing file too (FileExistsError), without a window between check and write (the
    temporary file is hard-linked to ``path``, which fails on anything there). Other OSErrors pass
    to the caller."""
    st = check_output(path, exclusive=exclusive)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    try:
        with os.fdopen(fd, "wb") as fh:
            if st is not None:
                os.fchmod(fh.fileno(), stat.S_IMODE(st.st_mode))
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        if exclusive:
            os.link(tmp, path, follow_symlinks=False)  # EEXIST on anything there, a link too
            os.unlink(tmp)
        else:
            os.replace(tmp, path)  # replaces a link planted since the check, never its target
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
