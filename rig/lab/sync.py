"""Pushing closed runs to the lab index: idempotent, resumable, offline-first.

* Idempotent: a run's key is ``<run id>:<data sha256>`` (UNIQUE in ``lab_runs``); keys already in
  the index are skipped after one query per batch of folders, and ``INSERT ... ON CONFLICT DO
  NOTHING`` settles a race with another rig process syncing the same run.
* Resumable: each run is one transaction (its row, instruments, criteria, results), so a sync
  killed at any point leaves whole runs only, and the next sync pushes the rest.
* Offline-first: the run folders are the record; an index that is down is one error line
  (:class:`~rig.lab.schema.LabUnavailableError`) and the next sync catches up.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rig.lab.schema import open_index, unavailable
from rig.lab.summary import RunSummary, sealed_key, summarize

if TYPE_CHECKING:
    import psycopg

BATCH = 200
"""Run folders whose keys are looked up in the index with one query."""


@dataclass
class SyncReport:
    """What a sync did: runs added, already there, still running (skipped), unreadable."""

    added: list[str] = field(default_factory=list)
    present: int = 0
    running: list[str] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)


def run_folders(runs_dir: Path) -> list[Path]:
    """Every run folder under ``runs_dir`` (holding ``run.sqlite``), oldest first."""
    if not runs_dir.is_dir():
        return []
    return sorted(p for p in runs_dir.iterdir() if (p / "run.sqlite").is_file())


def sync_runs(url: str, folders: Iterable[Path], *, timeout_s: float = 10.0,
              on_added: Callable[[RunSummary], None] | None = None) -> SyncReport:  # fmt: skip
    """Push every closed run of ``folders`` that the index lacks; see the module docstring."""
    import psycopg

    report = SyncReport()
    conn = open_index(url, timeout_s=timeout_s)
    try:
        todo = list(folders)
        for start in range(0, len(todo), BATCH):
            batch = todo[start : start + BATCH]
            keys = {f: sealed_key(f) for f in batch}
            known = _known(conn, [k for k in keys.values() if k is not None])
            for folder in batch:
                key = keys[folder]
                if key is not None and key in known:
                    report.present += 1
                    continue
                try:
                    summary = summarize(folder)
                except Exception as exc:  # a damaged folder must not stop the others
                    report.unreadable.append(f"{folder.name} ({type(exc).__name__}: {exc})")
                    continue
                if summary is None:
                    report.running.append(folder.name)
                elif insert_run(conn, summary):
                    report.added.append(summary.run_id)
                    if on_added is not None:
                        on_added(summary)
                else:
                    report.present += 1
    except psycopg.Error as exc:  # the server went away mid-sync: what is committed stays
        raise unavailable(url, exc) from None
    finally:
        conn.close()
    return report


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
