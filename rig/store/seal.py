"""The run's seal: a digest of the recorded data, written once when the run is closed.

The digest identifies the *data*, not the file: every row of every table, in a canonical order
(sorted by all columns), each value in its exact text form (``repr`` of a float round-trips). So
SQLite's page layout, a checkpoint, a VACUUM or a copy of the file do not change it; any changed,
added or removed row does. ``seal.json`` beside ``run.sqlite`` records it with the digests of the
procedure and rig configuration copies; reports print it; :func:`verify_run` recomputes it.

The seal also lists the database's schema objects (tables added or dropped are changes the data
digest cannot see). Beside it, ``manifest.json`` lists every other file of the folder with its
SHA-256 and is bound to the seal by the seal's own SHA-256: written with the seal when the run
closes, and rewritten by the rig whenever it writes a file into the closed run (the reports, an
export), so :func:`verify_run` can tell changed data from an edited, deleted or added file. Not
listed: ``run.sqlite`` (the data digest covers it), its WAL/SHM files, ``seal.json``,
``manifest.json`` and the live channel of a running run (``live.json``, ``control/``).

The seal is not a signature: someone with write access can change data and seal alike. It makes
an accident, a later write or a stale report visible; archive the run folder (or the report's
digest) somewhere write-once if tampering is a concern.

Every file is read without following links (:mod:`rig.store.safe_files`).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import re
import sqlite3
import stat
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rig.errors import UserInputError
from rig.store import safe_files

SEAL_FILE = "seal.json"
SEAL_FORMAT = 1
MANIFEST_FILE = "manifest.json"
MANIFEST_FORMAT = 1
DB_FILE = "run.sqlite"
UNLISTED = frozenset({DB_FILE, f"{DB_FILE}-wal", f"{DB_FILE}-shm", f"{DB_FILE}-journal",
                      SEAL_FILE, MANIFEST_FILE, "live.json", "control"})  # fmt: skip
"""Top-level names the manifest does not list (see the module docstring)."""
_TEMPORARY = re.compile(r"^\.(.+\.[0-9a-f]{12}\.tmp|run\.sqlite\.new)$")
"""A file being written (safe_files' temporary beside its target, a new store being built)."""
MAX_LISTED = 10_000
"""A folder with more entries than this is not listed file by file (verify says so)."""
MAX_META_BYTES = 1 << 20
"""seal.json and manifest.json are small; a larger one is refused unread."""
TABLES = ("meta", "steps", "commands", "events", "channels", "samples", "results")
"""Every table of the run store, in digest order."""
SEALED_FILES = ("procedure.yaml", "rig.toml")
"""Copies made when the run started; their digests are in the seal."""
REPORT_FILES = ("report.txt", "report.html", "report.pdf")
_DIGEST_IN_REPORT = re.compile(rb"data sha256 ([0-9a-f]{64})", re.IGNORECASE)


class DamagedRunError(UserInputError):
    """A run's database cannot be read (truncated, overwritten): the other runs are unaffected."""


def damaged(folder: Path, exc: BaseException) -> DamagedRunError:
    """One line naming the damaged run and what to do."""
    return DamagedRunError(
        f"{folder}: run.sqlite is damaged ({exc}); the run cannot be read: restore the folder"
        " from a backup or move it out of the runs folder"
    )


def data_digest(db_path: Path) -> tuple[str, dict[str, int]]:
    """SHA-256 (hex) of every table's rows in canonical order, and the row count per table.

    Opens the database read-only; a table the file lacks counts as empty.
    """
    return _tables_digest(db_path, TABLES)


def _tables_digest(db_path: Path, tables: tuple[str, ...]) -> tuple[str, dict[str, int]]:
    """SHA-256 (hex) of ``tables``' rows in canonical order, and the row count per table."""
    h = hashlib.sha256()
    counts: dict[str, int] = {}
    con = _open_ro(db_path)
    try:
        present = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        for table in tables:
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


MEASUREMENT_TABLES = ("steps", "commands", "channels", "samples", "results")
"""What a run measured and did, without its dates and identity (meta) or its log (events)."""


def measurement_digest(db_path: Path) -> str:
    """SHA-256 (hex) of what a run measured and did (:data:`MEASUREMENT_TABLES`, every row in
    canonical order): in simulated time the same procedure, rig file and seed give the same one
    on any machine and load (ADR 0038)."""
    return _tables_digest(db_path, MEASUREMENT_TABLES)[0]


def _open_ro(db_path: Path) -> sqlite3.Connection:
    """A read-only connection to the run's database, after checking it is a regular file (a
    link is refused: :class:`~rig.store.safe_files.UnsafeFileError`)."""
    safe_files.check_folder(db_path.parent)
    safe_files.regular_file(db_path)
    return sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=10.0)


def schema_objects(db_path: Path) -> list[str]:
    """Every table, index, view and trigger of the database as ``"<type> <name>"``, sorted."""
    con = _open_ro(db_path)
    try:
        rows = con.execute("SELECT type, name FROM sqlite_master").fetchall()
    finally:
        con.close()
    return sorted(f"{kind} {name}" for kind, name in rows)


def file_digest(path: Path) -> str:
    """SHA-256 (hex) of a regular file's bytes (never read through a link)."""
    h = hashlib.sha256()
    with os.fdopen(safe_files.open_fd(path), "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def seal_run(folder: Path) -> dict[str, Any]:
    """Write ``seal.json`` for a closed run (atomically, never through a link) and a fresh
    ``manifest.json`` of the folder's files bound to it; returns the seal."""
    safe_files.check_folder(folder)
    digest, counts = data_digest(folder / DB_FILE)
    status = _status(folder / DB_FILE)
    seal = {
        "format": SEAL_FORMAT,
        "data_sha256": digest,
        "rows": counts,
        "status": status,
        "sealed_at": _now(),
        "files": {
            name: file_digest(folder / name)
            for name in SEALED_FILES
            if safe_files.is_regular_file(folder / name)
        },
        "schema": schema_objects(folder / DB_FILE),
    }
    text = json.dumps(seal, indent=2) + "\n"
    safe_files.write_text(folder / SEAL_FILE, text)
    files, _ = list_files(folder)
    _write_manifest(folder, text.encode(), digest, files, "the run was sealed")
    return seal


def _now() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def _write_manifest(
    folder: Path, seal_bytes: bytes, data_sha256: str, files: dict[str, str], why: str
) -> None:
    manifest = {
        "format": MANIFEST_FORMAT,
        "seal_sha256": hashlib.sha256(seal_bytes).hexdigest(),
        "data_sha256": data_sha256,
        "written_at": _now(),
        "written_because": why,
        "files": dict(sorted(files.items())),
    }
    safe_files.write_text(folder / MANIFEST_FILE, json.dumps(manifest, indent=2) + "\n")


def list_files(folder: Path) -> tuple[dict[str, str], list[str]]:
    """The folder's files the manifest lists, by path relative to ``folder`` (``a/b.csv``): the
    SHA-256 of each regular file, and the entries that are not regular files (a link, a FIFO: never
    listed, always reported). Links are never followed, into files or folders."""
    files: dict[str, str] = {}
    odd: list[str] = []
    todo: list[tuple[Path, str]] = [(folder, "")]
    seen = 0
    while todo:
        here, prefix = todo.pop()
        with os.scandir(here) as entries:
            for entry in entries:
                rel = prefix + entry.name
                if (not prefix and entry.name in UNLISTED) or _TEMPORARY.match(entry.name):
                    continue
                seen += 1
                if seen > MAX_LISTED:
                    odd.append(f"more than {MAX_LISTED} entries (not all listed)")
                    return files, odd
                mode = entry.stat(follow_symlinks=False).st_mode
                if stat.S_ISDIR(mode):
                    todo.append((Path(entry.path), rel + "/"))
                elif stat.S_ISREG(mode):
                    try:
                        files[rel] = file_digest(Path(entry.path))
                    except (OSError, safe_files.UnsafeFileError):
                        odd.append(rel)  # replaced by a link or removed while being read
                else:
                    odd.append(rel)
    return files, odd


def record_written(folder: Path, paths: Iterable[Path], why: str) -> bool:
    """Enter files the rig has just written into the closed run's folder in its manifest (their
    new SHA-256); paths outside the folder are ignored. The other entries are kept as they were;
    a run without a manifest (sealed before manifests, 2026-11-25) gets one listing what the
    folder holds now. False (nothing written) when the run has no seal: it is still running."""
    seal_path = folder / SEAL_FILE
    if not safe_files.is_regular_file(seal_path):
        return False
    seal_bytes = safe_files.read_bytes(seal_path, MAX_META_BYTES)
    seal = _json_dict(seal_bytes)
    manifest = read_manifest(folder)
    bound = (
        manifest is not None
        and manifest.get("seal_sha256") == hashlib.sha256(seal_bytes).hexdigest()
    )
    if manifest is not None and bound and isinstance(manifest.get("files"), dict):
        files = {str(k): str(v) for k, v in manifest["files"].items()}
    else:
        files, _ = list_files(folder)
    root = folder.resolve()
    for path in paths:
        try:
            rel = path.resolve().relative_to(root).as_posix()
        except ValueError:
            continue
        if rel.split("/", 1)[0] in UNLISTED:
            continue
        if safe_files.is_regular_file(path):
            files[rel] = file_digest(path)
    _write_manifest(folder, seal_bytes, str(seal.get("data_sha256")), files, why)
    return True


def _json_dict(data: bytes) -> dict[str, Any]:
    try:
        value = json.loads(data.decode("utf-8"))
    except ValueError:
        return {}
    return value if isinstance(value, dict) else {}


def read_manifest(folder: Path) -> dict[str, Any] | None:
    """The run's manifest, None when it has none; ``{}`` when it cannot be read."""
    path = folder / MANIFEST_FILE
    try:
        return _json_dict(safe_files.read_bytes(path, MAX_META_BYTES))
    except FileNotFoundError:
        return None
    except (OSError, safe_files.UnsafeFileError):
        return {}


def read_seal(folder: Path) -> dict[str, Any] | None:
    """The run's seal, or None when it has none (still running, or recorded before seals)."""
    path = folder / SEAL_FILE
    try:
        seal = _json_dict(safe_files.read_bytes(path, MAX_META_BYTES))
    except FileNotFoundError:
        return None
    except (OSError, safe_files.UnsafeFileError):
        seal = {}
    return seal if seal else {"data_sha256": "(unreadable seal.json)"}


def _status(db_path: Path) -> str:
    con = _open_ro(db_path)
    try:
        row = con.execute("SELECT value FROM meta WHERE key = 'status'").fetchone()
    except sqlite3.Error:
        row = None
    finally:
        con.close()
    return str(json.loads(row[0])) if row else "unknown"


AREAS = ("data", "reports", "files")
"""What :func:`verify_run` tells apart: the data (rows, tables, the sealed configuration copies),
the reports, and every other file of the folder."""


@dataclass
class Verification:
    """What :func:`verify_run` found: ``intact`` only when every check passed."""

    folder: Path
    data_sha256: str
    sealed: bool
    findings: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    changed: dict[str, list[str]] = field(default_factory=dict)
    """Area (:data:`AREAS`) -> its problems."""
    manifest: bool = False
    """The folder has a manifest: every file was checked, not only the data."""

    @property
    def intact(self) -> bool:
        """The data, the sealed files and every report agree with the seal."""
        return self.sealed and not self.problems

    def problem(self, area: str, text: str) -> None:
        """Record a problem in ``area``."""
        self.problems.append(text)
        self.changed.setdefault(area, []).append(text)


def verify_run(folder: Path) -> Verification:
    """Recompute the run's digests and compare them with its seal, its manifest (every file of the
    folder, added and deleted ones included) and the digest every report states."""
    safe_files.check_folder(folder)
    digest, counts = data_digest(folder / DB_FILE)
    seal = read_seal(folder)
    out = Verification(folder, digest, seal is not None)
    if seal is None:
        out.problem("data",
            "not sealed: the run is still running or was recorded before runs were sealed")  # fmt: skip
    elif seal.get("data_sha256") != digest:
        changed = [
            f"{t} {seal.get('rows', {}).get(t)} -> {n} rows"
            for t, n in counts.items()
            if seal.get("rows", {}).get(t) != n
        ]
        out.problem("data",
            f"data changed since the run was sealed: sealed {seal.get('data_sha256')}, now"
            f" {digest}" + (f" ({', '.join(changed)})" if changed else " (same row counts)"))  # fmt: skip
    else:
        out.findings.append(
            f"data sha256 {digest} matches the seal ({seal.get('sealed_at')}, status"
            f" {seal.get('status')}; {sum(counts.values())} rows)"
        )
    if seal is not None:
        _check_schema(out, seal)
        for name, sealed_digest in (seal.get("files") or {}).items():
            path = folder / str(name)
            try:
                same = file_digest(path) == sealed_digest
            except FileNotFoundError:
                out.problem("data", f"{name} is missing (it was sealed)")
                continue
            except safe_files.UnsafeFileError:
                same = False
            if same:
                out.findings.append(f"{name} matches the seal")
            else:
                out.problem("data", f"{name} changed since the run was sealed")
        _check_manifest(out)
    for name in REPORT_FILES:
        path = folder / name
        try:
            text = safe_files.read_bytes(path)
        except FileNotFoundError:
            continue
        except safe_files.UnsafeFileError as exc:
            out.problem("reports", str(exc))
            continue
        stated = {m.decode().lower() for m in _DIGEST_IN_REPORT.findall(text)}
        if not stated:
            out.problem("reports", f"{name} states no data sha256; rebuild it with 'rig report'")
        elif stated != {digest}:
            out.problem("reports",
                f"{name} states data sha256 {', '.join(sorted(stated))}, the data is {digest};"
                " rebuild it with 'rig report'")  # fmt: skip
        else:
            out.findings.append(f"{name} states the same data sha256")
    return out


def _check_schema(out: Verification, seal: dict[str, Any]) -> None:
    """Tables (indexes, views, triggers) added to or dropped from run.sqlite since the seal."""
    now = set(schema_objects(out.folder / DB_FILE))
    sealed = seal.get("schema")
    if isinstance(sealed, list):
        before = {str(x) for x in sealed}
        for obj in sorted(now - before):
            out.problem("data", f"{obj} added to run.sqlite since the run was sealed")
        for obj in sorted(before - now):
            out.problem("data", f"{obj} dropped from run.sqlite since the run was sealed")
        if now == before:
            out.findings.append(f"run.sqlite has the sealed tables ({len(now)} schema objects)")
    else:  # sealed before the seal listed the schema: any table the rig does not write is new
        for obj in sorted(o for o in now if o.startswith("table ") and o[6:] not in TABLES):
            out.problem("data", f"{obj} in run.sqlite is not one the rig writes")


def _check_manifest(out: Verification) -> None:
    """Every file of the folder against the manifest: edited, deleted, added."""
    folder = out.folder
    manifest = read_manifest(folder)
    if manifest is None:
        out.findings.append(
            "no manifest.json (sealed before 2026-11-25): the data and the sealed copies are"
            " checked, the reports only for the digest they state, other files not at all"
        )
        return
    out.manifest = True
    try:
        seal_bytes = safe_files.read_bytes(folder / SEAL_FILE, MAX_META_BYTES)
    except (OSError, safe_files.UnsafeFileError):
        seal_bytes = b""
    listed = manifest.get("files")
    if not isinstance(listed, dict):
        out.problem("files", "manifest.json is unreadable; rebuild the reports with 'rig report'"
                    " only after finding out who changed it")  # fmt: skip
        listed = {}
    elif manifest.get("seal_sha256") != hashlib.sha256(seal_bytes).hexdigest():
        out.problem("files", "manifest.json does not belong to this seal.json (one of them was"
                    " rewritten by hand or copied from another run)")  # fmt: skip
    files, odd = list_files(folder)
    for rel in odd:
        out.problem(_area(rel), f"{rel} is a link or not a regular file (added to the folder)")
    edited = deleted = added = 0
    for rel, sealed_digest in sorted(listed.items()):
        if rel not in files:
            if rel not in odd:
                out.problem(_area(rel), f"{rel} deleted (the rig wrote it)")
                deleted += 1
        elif files[rel] != sealed_digest:
            out.problem(_area(rel), f"{rel} edited since the rig wrote it")
            edited += 1
    for rel in sorted(set(files) - set(listed)):
        out.problem(_area(rel), f"{rel} added (the rig did not write it)")
        added += 1
    if not (edited or deleted or added or odd):
        out.findings.append(
            f"every file matches manifest.json ({len(files)} files, {manifest.get('written_at')})"
        )


def _area(rel: str) -> str:
    return "reports" if rel in REPORT_FILES else "files"
