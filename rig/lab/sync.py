"""Pushing closed runs to the lab index: idempotent, resumable, offline-first.

* Idempotent: a run's key is ``<run id>:<data sha256>`` (UNIQUE in ``lab_runs``); keys already in
  the index are skipped after one query per batch of folders, and ``INSERT ... ON CONFLICT DO
  NOTHING`` settles a race with another rig process syncing the same run.
* Resumable: each run is one transaction (its row, instruments, criteria, results), so a sync
  killed at any point leaves whole runs only, and the next sync pushes the rest.
* Offline-first: the run folders are the record; an index that is down is one error line
  (:class:`~rig.lab.schema.LabUnavailableError`) and the next sync catches up.
* Checked: only sealed runs are pushed, and each seal is recomputed first (:func:`seal_problem`,
  as ``rig verify`` does); a run whose data, tables, configuration copies or other files no
  longer match its seal is refused, and so is one with a number outside its physical range
  (:mod:`rig.lab.bounds`) or one the index cannot store (a NUL byte in a string, a constraint).
  Each refusal is one line in the report and a row of ``lab_refusals`` (``rig lab audit``); the
  other runs sync. A run without a seal is skipped (one line, and a ``lab_refusals`` row).
* Owned: the seal is a checksum, not a signature; anyone who can write a runs folder can make a
  sealed run from nothing. So a run folder (or one of its files) that group or other may write,
  or that another account owns, is skipped unread with one line naming the permission and the
  fix (:func:`folder_problem`), and ``rig lab sync`` refuses a runs folder so exposed
  (:func:`check_runs_dir`). See docs/lab.md.
* Bounded: every statement, lock waits included, ends within ``timeout_s`` (the session's
  ``statement_timeout`` and ``lock_timeout``), so a locked table cannot hold a closing run.
"""

from __future__ import annotations

import os
import sqlite3
import stat
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rig.errors import UserInputError
from rig.lab.bounds import out_of_range
from rig.lab.schema import open_index, unavailable
from rig.lab.summary import RunSummary, run_key, sealed_key, summarize
from rig.store import safe_files
from rig.store.seal import verify_run

if TYPE_CHECKING:
    import psycopg


def unstorable() -> tuple[type[Exception], ...]:
    """Errors that are one run's (a string PostgreSQL cannot hold, a constraint, a number out of
    range), not the index's."""
    import psycopg

    return (psycopg.DataError, psycopg.IntegrityError, ValueError, TypeError, OverflowError)


BATCH = 200
"""Run folders whose keys are looked up in the index with one query."""


@dataclass
class SyncReport:
    """What a sync did: runs added, already there, still running (skipped), unreadable, refused
    (changed since sealed, a value out of range), not stored (the index refused them), skipped
    (not sealed, or a folder other accounts may write); the last four with the reason."""

    added: list[str] = field(default_factory=list)
    present: int = 0
    running: list[str] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    not_stored: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)


def _trusted(uid: int) -> bool:
    """Files of this account or root are the rig's."""
    return uid in (os.geteuid(), 0)


def path_problem(path: Path, what: str, *, follow: bool = False) -> str | None:
    """Why ``path`` (a folder or file of runs) may hold another account's data, or None: owned by
    another account, or writable by group or other. One line naming the fix. A link is judged
    by what it points to when ``follow``, else not at all: the run's readers refuse links with
    their own line (:mod:`rig.store.safe_files`)."""
    try:
        st = os.stat(path) if follow else os.lstat(path)
    except FileNotFoundError:
        return None
    if stat.S_ISLNK(st.st_mode):
        return None
    if not _trusted(st.st_uid):
        return (f"{what} {path} is owned by uid {st.st_uid}, not by this account (uid"
                f" {os.geteuid()}): another account made it; check it and move it out of the runs"
                " folder")  # fmt: skip
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o022:
        who = " and ".join(w for w, bit in (("group", 0o020), ("other", 0o002)) if mode & bit)
        return (f"{what} {path} can be written by {who} (mode {mode:o}): anyone there can forge a"
                f" sealed run; chmod go-w {path}")  # fmt: skip
    return None


def check_runs_dir(runs_dir: Path) -> None:
    """Refuse (UserInputError, one line) a runs folder another account may write or owns."""
    problem = path_problem(runs_dir, "runs folder", follow=True)
    if problem is not None:
        raise UserInputError(f"{problem}; nothing was pushed")


LIVE_ONLY = frozenset({"live.json", "control"})
"""Entries of a running run's live channel (checked by the run itself, ADR 0016)."""


def folder_problem(folder: Path) -> str | None:
    """Why the run in ``folder`` may not be trusted as the rig's own (see :func:`path_problem`):
    the folder itself, then each entry of it (files and folders, one level)."""
    problem = path_problem(folder, "run folder")
    if problem is not None:
        return problem
    try:
        names = sorted(os.listdir(folder))
    except OSError as exc:
        return f"run folder {folder} cannot be listed ({exc.strerror})"
    for name in names:
        if name in LIVE_ONLY:
            continue
        problem = path_problem(folder / name, "run file")
        if problem is not None:
            return problem
    return None


def run_folders(runs_dir: Path) -> list[Path]:
    """Every run folder under ``runs_dir`` (holding ``run.sqlite``, even a link that the sync then
    refuses), oldest first."""
    if not runs_dir.is_dir():
        return []
    return sorted(p for p in runs_dir.iterdir() if os.path.lexists(p / "run.sqlite"))


def sync_runs(url: str, folders: Iterable[Path], *, timeout_s: float = 10.0,
              on_added: Callable[[RunSummary], None] | None = None) -> SyncReport:  # fmt: skip
    """Push every closed run of ``folders`` that the index lacks; see the module docstring.
    ``timeout_s`` bounds the connection and every statement (a lock wait included)."""
    import psycopg

    report = SyncReport()
    conn = open_index(url, timeout_s=timeout_s, statement_timeout_s=timeout_s)
    try:
        todo = list(folders)
        for start in range(0, len(todo), BATCH):
            batch = todo[start : start + BATCH]
            keys = {f: _sealed_key(f) for f in batch}
            known = _known(conn, [k for k in keys.values() if k is not None])
            for folder in batch:
                key = keys[folder]
                if key is not None and key in known:
                    report.present += 1
                    continue
                _sync_one(conn, folder, report, on_added)
    except psycopg.Error as exc:  # the server went away mid-sync: what is committed stays
        raise unavailable(url, exc) from None
    finally:
        conn.close()
    return report


def _sealed_key(folder: Path) -> str | None:
    try:
        return sealed_key(folder)
    except safe_files.UnsafeFileError:
        return None  # summarize says why


def _sync_one(conn: psycopg.Connection[Any], folder: Path, report: SyncReport,
              on_added: Callable[[RunSummary], None] | None) -> None:  # fmt: skip
    """One run: its folder's owner and permissions checked, read, checked against its seal and
    the physical ranges, inserted; a refusal is reported and recorded."""
    exposed = folder_problem(folder)
    if exposed is not None:  # not even opened: reading a run may mark and seal it
        report.skipped.append(f"{folder.name}: {exposed}")
        return
    try:
        summary = summarize(folder)
        problem = None if summary is None else seal_problem(folder, summary)
    except Exception as exc:  # a damaged folder must not stop the others
        report.unreadable.append(f"{folder.name} ({type(exc).__name__}: {exc})")
        return
    if summary is None:
        report.running.append(folder.name)
        return
    if summary.data_sha256 is None:
        why = f"not sealed, so its data cannot be checked; 'rig verify {folder}' says more"
        report.skipped.append(f"{folder.name}: {why}")
        record_refusal(conn, summary, "not sealed", why)
        return
    if problem is not None:
        report.refused.append(f"{folder.name}: {problem}")
        record_refusal(conn, summary, "changed since sealed", problem)
        return
    beyond = out_of_range(summary)
    if beyond is not None:
        report.refused.append(f"{folder.name}: {beyond}; not stored")
        record_refusal(conn, summary, "value out of range", beyond)
        return
    try:
        added = insert_run(conn, summary)
    except unstorable() as exc:
        if conn.closed or conn.broken:
            raise
        reason = _one_line(exc)
        report.not_stored.append(f"{folder.name}: {reason}")
        record_refusal(conn, summary, "cannot be stored", reason)
        return
    if added:
        report.added.append(summary.run_id)
        if on_added is not None:
            on_added(summary)
    else:
        report.present += 1


def seal_problem(folder: Path, summary: RunSummary) -> str | None:
    """Why a run may not be pushed: no seal, or its data, tables, configuration copies or other
    files no longer match the seal (recomputed now, as ``rig verify`` does; the reports are not
    held to it: the index takes nothing from them); None when it may."""
    if summary.data_sha256 is None:
        return f"not sealed; 'rig verify {folder}' says more"
    try:
        result = verify_run(folder)
    except (sqlite3.Error, OSError, safe_files.UnsafeFileError) as exc:
        return f"its data cannot be read to check the seal ({exc})"
    if result.data_sha256 != summary.data_sha256:
        return (f"its data changed since the run was sealed (sealed {summary.data_sha256}, now"
                f" {result.data_sha256}); 'rig verify {folder}' says what")  # fmt: skip
    changed = result.changed.get("data", []) + result.changed.get("files", [])
    return f"{changed[0]}; 'rig verify {folder}' says more" if changed else None


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__).replace("\x00", "\\x00")


def _clean(text: str | None) -> str | None:
    """A string PostgreSQL can store: NUL bytes shown escaped."""
    return None if text is None else text.replace("\x00", "\\x00")


def record_refusal(conn: psycopg.Connection[Any], s: RunSummary, kind: str, reason: str) -> None:
    """A row of ``lab_refusals`` for ``rig lab audit`` (per run, seal and kind: a refusal seen
    again counts one more attempt). Best effort: the refusal is reported either way."""
    try:
        with conn.transaction(), conn.cursor() as cur:
            cur.execute(
                "INSERT INTO lab_refusals (run_uid, run_id, rig, host, kind, reason, sealed_sha256)"
                " VALUES (%s, %s, %s, %s, %s, %s, %s) ON CONFLICT (run_uid, kind) DO UPDATE SET"
                " reason = EXCLUDED.reason, last_at = now(),"
                " attempts = lab_refusals.attempts + 1",
                (_clean(run_key(s.run_id, s.data_sha256)), _clean(s.run_id), _clean(s.rig),
                 _clean(s.host), kind, _clean(reason), _clean(s.data_sha256)),
            )  # fmt: skip
    except unstorable():
        if conn.closed or conn.broken:
            raise


def _known(conn: psycopg.Connection[Any], keys: list[str]) -> set[str]:
    """The keys the index already holds."""
    if not keys:
        return set()
    with conn.cursor() as cur:
        cur.execute("SELECT run_uid FROM lab_runs WHERE run_uid = ANY(%s)", (keys,))
        found = {str(r[0]) for r in cur.fetchall()}
    conn.rollback()
    return found


def insert_run(conn: psycopg.Connection[Any], s: RunSummary) -> bool:
    """One run in one transaction; False when the index had it already (nothing written)."""
    with conn.transaction(), conn.cursor() as cur:
        cur.execute(
            "INSERT INTO lab_runs (run_uid, run_id, rig, host, procedure, dut_serial, lot,"
            " operator, status, verdict, started_at, sealed_at, software_version, data_sha256,"
            " report_files) VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s)"
            " ON CONFLICT (run_uid) DO NOTHING RETURNING id",
            (s.uid, s.run_id, s.rig, s.host, s.procedure, s.dut_serial, s.lot, s.operator,
             s.status, s.verdict, s.started_at, s.sealed_at, s.software_version, s.data_sha256,
             s.report_files),
        )  # fmt: skip
        row = cur.fetchone()
        if row is None:
            return False
        run = row[0]
        if s.instruments:
            cur.executemany(
                "INSERT INTO lab_instruments VALUES (%s, %s, %s, %s, %s, %s, %s)",
                [(run, i.name, i.kind, i.serial, i.calibrated_on, i.certificate_expires,
                  i.expired) for i in s.instruments],
            )  # fmt: skip
        if s.criteria:
            cur.executemany(
                "INSERT INTO lab_criteria VALUES (%s, %s, %s, %s, %s, %s, %s, %s)"
                " ON CONFLICT DO NOTHING",
                [(run, c.name, c.value, c.unit, c.min, c.max, c.margin, c.verdict)
                 for c in s.criteria],
            )  # fmt: skip
        if s.results:
            cur.executemany(
                "INSERT INTO lab_results VALUES (%s, %s, %s, %s, %s) ON CONFLICT DO NOTHING",
                [(run, r.source, r.name, r.value, r.sigma) for r in s.results],
            )
    return True
