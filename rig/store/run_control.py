"""The files through which a run in progress is watched and operated from another process.

A running rig process publishes its live state as ``live.json`` in its run folder (replaced
atomically twice a second, never through a link) and takes requests from ``control/``: one JSON
file per request, written under a temporary name and renamed, so the run reads only whole requests.
The web page (``rig serve``) writes requests and reads the state; the run never waits for a reader,
and a reader that vanishes costs the run nothing (ADR 0016).

Only the run's owner operates it: ``control/`` is created 0700, and the run takes a request only
from a regular file (not a link) owned by its own account (or root) in a ``control/`` folder that is
not a link, is owned by it (or root) and is writable by nobody else. Anything else is left alone
and reported once (:func:`take_requests`), so an account that can write the runs folder can get in
the way of the page but cannot pause, abort or answer.

Requests: ``{"action": "pause" | "resume" | "abort"}`` and ``{"action": "answer", "prompt": ID,
"yes": bool}`` for the operator prompt ``ID`` (a number the live state shows with the text).
"""

from __future__ import annotations

import contextlib
import json
import os
import stat
import time
import uuid
from pathlib import Path
from typing import Any

from rig.errors import UserInputError
from rig.store import safe_files

LIVE_FILE = "live.json"
CONTROL_DIR = "control"
ACTIONS = ("pause", "resume", "abort", "answer")
MAX_LIVE_BYTES = 4 * 1024 * 1024
"""A ``live.json`` larger than this is not read (it is ~10 kB)."""
MAX_REQUEST_BYTES = 64 * 1024
"""A request file larger than this is not read (it is < 100 bytes)."""


def write_live(folder: Path, state: dict[str, Any]) -> None:
    """Replace ``live.json`` with ``state`` (atomic: a reader sees the old or the new file; a link
    planted there is replaced, its target left alone)."""
    safe_files.write_text(folder / LIVE_FILE, json.dumps(state, separators=(",", ":")))


def read_live(folder: Path) -> dict[str, Any] | None:
    """The last published live state, or None when there is none (or it is a link, or damaged)."""
    try:
        value = json.loads(safe_files.read_text(folder / LIVE_FILE, MAX_LIVE_BYTES))
    except (OSError, ValueError, safe_files.UnsafeFileError):
        return None
    return value if isinstance(value, dict) else None


def _trusted(uid: int) -> bool:
    """Files and folders of this account or root are the run owner's."""
    return uid in (os.geteuid(), 0)


def box_problem(box: Path) -> str | None:
    """Why ``box`` (a run's ``control/``) may not be trusted, or None if it may."""
    try:
        st = os.lstat(box)
    except FileNotFoundError:
        return None
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        return f"control folder {box} ignored: it is a link or not a folder (remove it)"
    if not _trusted(st.st_uid):
        return (f"control requests from uid {st.st_uid} ignored: {box} is that account's, not"
                " the run owner's (remove it)")  # fmt: skip
    if stat.S_IMODE(st.st_mode) & 0o022:
        return (f"control folder {box} ignored: other accounts may write to it (mode"
                f" {stat.S_IMODE(st.st_mode):o}); chmod 700 it")  # fmt: skip
    return None


def open_box(folder: Path) -> Path:
    """Create the run's ``control/`` folder, 0700 (the run does this as it starts, so nobody else
    creates it first); an existing one is left as it is. Returns it."""
    box = folder / CONTROL_DIR
    with contextlib.suppress(FileExistsError):
        os.mkdir(box, 0o700)
        os.chmod(box, 0o700)  # the umask aside
    return box


def request(folder: Path, action: str, *, prompt: int | None = None, yes: bool = False) -> None:
    """Queue a request for the run in ``folder`` (raises UserInputError for a bad one, or when the
    request box is not the owner's)."""
    if action not in ACTIONS:
        raise UserInputError(f"unknown run request {action!r}; use one of {', '.join(ACTIONS)}")
    body: dict[str, Any] = {"action": action, "t": time.time()}
    if action == "answer":
        if not isinstance(prompt, int) or isinstance(prompt, bool) or not 0 <= prompt < 2**53:
            raise UserInputError("an answer needs the whole number of the prompt it answers")
        body |= {"prompt": prompt, "yes": bool(yes)}
    box = open_box(safe_files.check_folder(folder))
    problem = box_problem(box)
    if problem is not None:
        raise UserInputError(problem.replace(" ignored", " not used", 1))
    name = f"{time.time_ns():020d}-{uuid.uuid4().hex[:8]}.json"
    safe_files.write_text(box / name, json.dumps(body), mode=0o600)


def take_requests(folder: Path, refused: list[str] | None = None) -> list[dict[str, Any]]:
    """Remove and return the queued requests, oldest first; unreadable ones are dropped. A request
    not from the run's owner (see the module) is not taken: one line saying so goes to
    ``refused`` (the same line for every request of one account, for the caller to report once)."""
    box = folder / CONTROL_DIR
    problem = box_problem(box)
    if problem is not None:
        if refused is not None:
            refused.append(problem)
        return []
    try:
        names = sorted(n for n in os.listdir(box) if n.endswith(".json") and not n.startswith("."))
    except (FileNotFoundError, NotADirectoryError):
        return []
    out = []
    for name in names:
        path = box / name
        body = None
        try:
            fd = safe_files.open_fd(path)
            with os.fdopen(fd, "rb") as fh:
                uid = os.fstat(fh.fileno()).st_uid
                if not _trusted(uid):
                    if refused is not None:
                        refused.append(f"control requests from uid {uid} ignored: the run takes"
                                       " requests only from its owner's account")  # fmt: skip
                    body = None
                else:
                    body = json.loads(fh.read(MAX_REQUEST_BYTES + 1)[:MAX_REQUEST_BYTES])
        except safe_files.UnsafeFileError:
            if refused is not None:
                refused.append(f"control request {name} ignored: a link or not a regular file")
        except (OSError, ValueError):
            body = None
        try:
            path.unlink()  # a link is removed itself, never its target
        except FileNotFoundError:
            continue  # taken by someone else
        except OSError:
            pass
        if isinstance(body, dict) and body.get("action") in ACTIONS:
            out.append(body)
    return out


def run_page_url(page_url: str, run_id: str) -> str:
    """The address of run ``run_id``'s page on the server at ``page_url`` (which may carry
    ``?token=``): the run id quoted as one path segment, the token kept."""
    from urllib.parse import quote, urlsplit, urlunsplit

    parts = urlsplit(page_url)
    path = parts.path.rstrip("/") + "/runs/" + quote(run_id, safe="")
    return urlunsplit((parts.scheme, parts.netloc, path, parts.query, ""))
