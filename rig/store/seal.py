"""The run's seal: a digest of the recorded data, written once when the run is closed.

The digest identifies the *data*, not the file: every row of every table, in a canonical order
(sorted by all columns), each value in its exact text form (``repr`` of a float round-trips). So
SQLite's page layout, a checkpoint, a VACUUM or a copy of the file do not change it; any changed,
added or removed row does. ``seal.json`` beside ``run.sqlite`` records it with the digests of the
procedure and rig configuration copies; reports print it; :func:`verify_run` recomputes it.

The seal is not a signature: someone with write access can change data and seal alike. It makes
an accident, a later write or a stale report visible; archive the run folder (or the report's
digest) somewhere write-once if tampering is a concern.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import re
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

SEAL_FILE = "seal.json"
SEAL_FORMAT = 1
TABLES = ("meta", "steps", "commands", "events", "channels", "samples", "results")
"""Every table of the run store, in digest order."""
SEALED_FILES = ("procedure.yaml", "rig.toml")
"""Copies made when the run started; their digests are in the seal."""
REPORT_FILES = ("report.txt", "report.html", "report.pdf")
_DIGEST_IN_REPORT = re.compile(rb"data sha256 ([0-9a-f]{64})", re.IGNORECASE)


def data_digest(db_path: Path) -> tuple[str, dict[str, int]]:
    """SHA-256 (hex) of every table's rows in canonical order, and the row count per table.

    Opens the database read-only; a table the file lacks counts as empty.
    """
    h = hashlib.sha256()
    counts: dict[str, int] = {}
    con = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=10.0)
    try:
        present = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        for table in TABLES:
            h.update(f"\x00table {table}\n".encode())
            n = 0
            if table in present:
                ncols = len(con.execute(f"SELECT * FROM {table} LIMIT 0").description)
                order = ", ".join(str(i + 1) for i in range(ncols))
                for row in con.execute(f"SELECT * FROM {table} ORDER BY {order}"):
                    h.update(repr(row).encode())
                    h.update(b"\n")
                    n += 1
            counts[table] = n
    finally:
        con.close()
    return h.hexdigest(), counts


def file_digest(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def seal_run(folder: Path) -> dict[str, Any]:
    """Write ``seal.json`` for a closed run (atomically: a temporary file renamed); returns it."""
    digest, counts = data_digest(folder / "run.sqlite")
    status = _status(folder / "run.sqlite")
    seal = {
        "format": SEAL_FORMAT,
        "data_sha256": digest,
        "rows": counts,
        "status": status,
        "sealed_at": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "files": {
            name: file_digest(folder / name) for name in SEALED_FILES if (folder / name).exists()
        },
    }
    tmp = folder / f".{SEAL_FILE}.tmp"
    tmp.write_text(json.dumps(seal, indent=2) + "\n", encoding="utf-8")
    os.replace(tmp, folder / SEAL_FILE)
    return seal


def read_seal(folder: Path) -> dict[str, Any] | None:
    """The run's seal, or None when it has none (still running, or recorded before seals)."""
    path = folder / SEAL_FILE
    if not path.exists():
        return None
    try:
        seal = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {"data_sha256": "(unreadable seal.json)"}
    return seal if isinstance(seal, dict) else {"data_sha256": "(unreadable seal.json)"}


def _status(db_path: Path) -> str:
    con = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=10.0)
    try:
        row = con.execute("SELECT value FROM meta WHERE key = 'status'").fetchone()
    except sqlite3.Error:
        row = None
    finally:
        con.close()
    return str(json.loads(row[0])) if row else "unknown"


@dataclass
class Verification:
    """What :func:`verify_run` found: ``intact`` only when every check passed."""

    folder: Path
    data_sha256: str
    sealed: bool
    findings: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def intact(self) -> bool:
        """The data, the sealed files and every report agree with the seal."""
        return self.sealed and not self.problems


def verify_run(folder: Path) -> Verification:
    """Recompute the run's digests and compare them with its seal and with every report's."""
    digest, counts = data_digest(folder / "run.sqlite")
    seal = read_seal(folder)
    out = Verification(folder, digest, seal is not None)
    if seal is None:
        out.problems.append(
            "not sealed: the run is still running or was recorded before runs were sealed"
        )
    elif seal.get("data_sha256") != digest:
        changed = [
            f"{t} {seal.get('rows', {}).get(t)} -> {n} rows"
            for t, n in counts.items()
            if seal.get("rows", {}).get(t) != n
        ]
        out.problems.append(
            f"data changed since the run was sealed: sealed {seal.get('data_sha256')}, now"
            f" {digest}" + (f" ({', '.join(changed)})" if changed else " (same row counts)")
        )
    else:
        out.findings.append(
            f"data sha256 {digest} matches the seal ({seal.get('sealed_at')}, status"
            f" {seal.get('status')}; {sum(counts.values())} rows)"
        )
    if seal is not None:
        for name, sealed_digest in seal.get("files", {}).items():
            path = folder / name
            if not path.exists():
                out.problems.append(f"{name} is missing (it was sealed)")
            elif file_digest(path) != sealed_digest:
                out.problems.append(f"{name} changed since the run was sealed")
            else:
                out.findings.append(f"{name} matches the seal")
    for name in REPORT_FILES:
        path = folder / name
        if not path.exists():
            continue
        stated = {m.decode().lower() for m in _DIGEST_IN_REPORT.findall(path.read_bytes())}
        if not stated:
            out.problems.append(f"{name} states no data sha256; rebuild it with 'rig report'")
        elif stated != {digest}:
            out.problems.append(
                f"{name} states data sha256 {', '.join(sorted(stated))}, the data is {digest};"
                " rebuild it with 'rig report'"
            )
        else:
            out.findings.append(f"{name} states the same data sha256")
    return out
