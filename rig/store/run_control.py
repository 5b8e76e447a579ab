"""The files through which a run in progress is watched and operated from another process.

A running rig process publishes its live state as ``live.json`` in its run folder (replaced
atomically twice a second) and takes requests from ``control/``: one JSON file per request, written
under a temporary name and renamed, so the run reads only whole requests. The web page (``rig
serve``) writes requests and reads the state; the run never waits for a reader, and a reader that
vanishes costs the run nothing (ADR 0016).

Requests: ``{"action": "pause" | "resume" | "abort"}`` and ``{"action": "answer", "prompt": ID,
"yes": bool}`` for the operator prompt ``ID`` (a number the live state shows with the text).
"""

from __future__ import annotations

import json
import os
import time
import uuid
from pathlib import Path
from typing import Any

from rig.errors import UserInputError

LIVE_FILE = "live.json"
CONTROL_DIR = "control"
ACTIONS = ("pause", "resume", "abort", "answer")


def write_live(folder: Path, state: dict[str, Any]) -> None:
    """Replace ``live.json`` with ``state`` (atomic: a reader sees the old or the new file)."""
    tmp = folder / f".{LIVE_FILE}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(state, separators=(",", ":")), encoding="utf-8")
    os.replace(tmp, folder / LIVE_FILE)


def read_live(folder: Path) -> dict[str, Any] | None:
    """The last published live state, or None when the run never published one."""
    try:
        value = json.loads((folder / LIVE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def request(folder: Path, action: str, *, prompt: int | None = None, yes: bool = False) -> None:
    """Queue a request for the run in ``folder`` (raises UserInputError for a bad one)."""
    if action not in ACTIONS:
        raise UserInputError(f"unknown run request {action!r}; use one of {', '.join(ACTIONS)}")
    body: dict[str, Any] = {"action": action, "t": time.time()}
    if action == "answer":
        if prompt is None:
            raise UserInputError("an answer needs the prompt number it answers")
        body |= {"prompt": int(prompt), "yes": bool(yes)}
    box = folder / CONTROL_DIR
    box.mkdir(exist_ok=True)
    name = f"{time.time_ns():020d}-{uuid.uuid4().hex[:8]}.json"
    tmp = box / f".{name}.tmp"
    tmp.write_text(json.dumps(body), encoding="utf-8")
    os.replace(tmp, box / name)


def take_requests(folder: Path) -> list[dict[str, Any]]:
    """Remove and return the queued requests, oldest first; unreadable ones are dropped."""
    box = folder / CONTROL_DIR
    try:
        names = sorted(n for n in os.listdir(box) if n.endswith(".json") and not n.startswith("."))
    except FileNotFoundError:
        return []
    out = []
    for name in names:
        path = box / name
        try:
            body = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            body = None
        try:
            path.unlink()
        except FileNotFoundError:
            continue  # taken by someone else
        if isinstance(body, dict) and body.get("action") in ACTIONS:
            out.append(body)
    return out
