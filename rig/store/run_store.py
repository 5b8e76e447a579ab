"""The run store (contract): a run is a folder ``<runs-dir>/<run-id>/`` holding ``run.sqlite``.

SQLite in WAL mode. Writers queue rows; one thread commits them in small batches (every
``COMMIT_INTERVAL_S``), so a killed process loses at most the last batch.

A recording run holds a **lease**: the same thread renews the ``lease`` row of ``meta`` every
``LEASE_PERIOD_S`` (a count, the recorder's wall-clock time, its host, boot id, PID namespace and
PID). A reader that finds a run still ``running`` marks it ``incomplete`` (and seals it) only when
its recorder is gone: judged by the PID when the reader is provably in the recorder's boot and PID
namespace, else by the lease - expired when its wall-clock time is more than ``LEASE_EXPIRY_S``
away from the reader's *and* its count does not move for ``LEASE_WATCH_S``. So a reader in a
container or on another host sharing the runs folder never closes a live run, whatever the clocks.

A recorder can still be *stopped* long enough (SIGSTOP, a suspended VM) for such a reader to close
its run rightly. So the writer writes only while the run is still its own: every write (a batch,
the lease, metadata, a step, a result, the final status) is one ``BEGIN IMMEDIATE`` transaction
that first reads the status and writes nothing once it is no longer ``running``. The writer then
sets :attr:`RunWriter.closed_by_other`; the health monitor ends the run through the safe path, and
:meth:`RunWriter.close` neither writes the status nor seals again: the run stays as the reader
closed and sealed it (ADR 0036).

Clocks (ADR 0038): a run's own times and dates (its rows' ``t``, ``start_monotonic``,
``start_time``, ``end_time``, the folder's date) are on the process's clock (:mod:`timebase`),
so a run in simulated time is dated in simulated time (meta ``clock``: ``wall`` or
``simulated``). What other processes compare with their own clock stays on the wall clock: the
lease (its ``renewed_at`` and the commit thread that renews it, which is outside any simulated
clock and does not hold it up) and the expiry a reader judges.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import math
import queue
import sqlite3
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import timebase
from rig import host_identity
from rig.errors import StoreWriteError, UserInputError
from rig.store import safe_files
from rig.store.run_states import RunStatus
from rig.store.seal import damaged, seal_run
from rig.stored import JsonObject, JsonValue

COMMIT_INTERVAL_S = 0.2
"""At most this much data (plus one commit's duration) is at risk if the process is killed."""
LEASE_PERIOD_S = 1.0
"""The recorder renews its lease this often (s)."""
LEASE_EXPIRY_S = 30.0
"""A lease whose wall-clock time is further than this from the reader's (s) may have expired:
30 periods, beyond any stall of a live recorder and any clock offset of hosts kept in time."""
LEASE_WATCH_S = 3.0
"""How long a reader watches a lease that may have expired for a renewal (s; 3 periods): a live
recorder whose host's clock is off (or stopped) renews within it, and the run stays running."""

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS samples (t REAL NOT NULL, device TEXT NOT NULL, x REAL, y REAL, z REAL, t_unc REAL);
CREATE TABLE IF NOT EXISTS channels (t REAL NOT NULL, channel TEXT NOT NULL, commanded REAL, measured REAL, t_unc REAL);
CREATE TABLE IF NOT EXISTS commands (t REAL NOT NULL, step INTEGER, kind TEXT NOT NULL, payload TEXT);
CREATE TABLE IF NOT EXISTS events (t REAL NOT NULL, level TEXT NOT NULL, message TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS steps (idx INTEGER PRIMARY KEY, name TEXT, kind TEXT, t_start REAL, t_end REAL);
CREATE TABLE IF NOT EXISTS results (name TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE INDEX IF NOT EXISTS samples_device_t ON samples (device, t);
CREATE INDEX IF NOT EXISTS channels_channel_t ON channels (channel, t);
"""

TIME_UNCERTAINTY = "t_unc"
"""Column of ``samples`` and ``channels``: the row was taken within t +- t_unc (s, monotonic clock;
ADR 0020). NULL when unknown: commanded set-points, and runs recorded before it existed."""
TABLE_COLUMNS = {
    "samples": ("t", "device", "x", "y", "z", "t_unc"),
    "channels": ("t", "channel", "commanded", "measured", "t_unc"),
    "commands": ("t", "step", "kind", "payload"),
    "events": ("t", "level", "message"),
}


META_UPSERT = "INSERT OR REPLACE INTO meta VALUES (?, ?)"


def _meta_rows(values: dict[str, Any]) -> list[tuple[str, str]]:
    """Metadata as (key, JSON value) rows."""
    return [(k, json.dumps(v)) for k, v in values.items()]


def now_iso() -> str:
    """UTC time, seconds resolution, on the wall clock (when a file was written)."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def run_now(timespec: str = "seconds") -> str:
    """The date now on the run's clock (the process's, :mod:`timebase`): UTC, ISO 8601."""
    return dt.datetime.fromtimestamp(timebase.wall_time(), dt.UTC).isoformat(timespec=timespec)


def _connect(path: Path) -> sqlite3.Connection:
    con = sqlite3.connect(path, check_same_thread=False, timeout=10.0)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute(
        "PRAGMA synchronous=NORMAL"
    )  # WAL + NORMAL: an application crash loses nothing committed
    return con


class RunWriter:
    """Write side of one run. Thread safe: any thread may call the ``add_*`` methods."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.path = folder / "run.sqlite"
        self._con = _connect(self.path)
        self._con.executescript(SCHEMA)
        self._con.commit()
        self._queue: queue.SimpleQueue[tuple[str, tuple[Any, ...]] | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.rows_written = 0
        self.error: sqlite3.Error | None = None
        self.closed_by_other: str | None = None
        """Set (once) when another process closed this run (a reader marked it ``incomplete``
        while this one was stopped): the stored status and reason. Nothing more is written."""
        self.rows_dropped = 0
        """Rows not written because the run had been closed by another process."""
        self._lease = _lease_of(self._con)
        self._renew_lease()
        self._thread = threading.Thread(target=self._run, name="run-store", daemon=True)
        self._thread.start()

    # --- queued rows ----------------------------------------------------------------------------

    def add_sample(
        self, t: float, device: str, xyz: tuple[float, float, float], t_unc_s: float | None = None
    ) -> None:
        """A magnetometer reading (uT) taken at monotonic time ``t`` +- ``t_unc_s`` (s)."""
        self._queue.put(("samples", (t, device, *xyz, t_unc_s)))

    def add_channel(
        self,
        t: float,
        channel: str,
        commanded: float | None,
        measured: float | None,
        t_unc_s: float | None = None,
    ) -> None:
        """A commanded and/or measured current (A) of a coil or load channel; a measured value
        was taken within ``t`` +- ``t_unc_s`` (s)."""
        self._queue.put(("channels", (t, channel, commanded, measured, t_unc_s)))

    def add_command(self, t: float, step: int | None, kind: str, payload: dict[str, Any]) -> None:
        """A command the engine executed."""
        self._queue.put(("commands", (t, step, kind, json.dumps(payload))))

    def add_event(self, t: float, level: str, message: str) -> None:
        """A log event (info, warning, error, operator)."""
        self._queue.put(("events", (t, level, message)))

    # --- immediate writes -----------------------------------------------------------------------

    def _begin_if_ours(self) -> bool:
        """Open a write transaction (``BEGIN IMMEDIATE``, the lock held) if the run is still this
        writer's: its stored status is ``running`` (or not stored yet). Otherwise roll back, note
        who closed it in :attr:`closed_by_other` and return False: nothing may be written."""
        if self.closed_by_other is not None:
            return False
        con = self._con
        if con.in_transaction:
            con.commit()
        con.execute("BEGIN IMMEDIATE")
        stored = dict(con.execute("SELECT key, value FROM meta WHERE key IN ('status', 'reason')"))
        status = json.loads(stored["status"]) if "status" in stored else RunStatus.RUNNING
        if status == RunStatus.RUNNING:
            return True
        con.rollback()
        reason = json.loads(stored["reason"]) if "reason" in stored else "no reason stored"
        self.closed_by_other = f"{status} ({reason})"
        return False

    @contextlib.contextmanager
    def _writing(self) -> Iterator[bool]:
        """Hold the lock inside a write transaction if the run is still ours (yields whether it
        is: write only then); a database error becomes a one-line :class:`StoreWriteError`."""
        with self._lock:
            try:
                ours = self._begin_if_ours()
                try:
                    yield ours
                except BaseException:
                    if self._con.in_transaction:
                        self._con.rollback()
                    raise
            except sqlite3.Error as exc:
                self.error = exc
                raise StoreWriteError(
                    f"cannot write the run data to {self.path} ({exc}): is the disk full? Free"
                    f" space under {self.folder.parent}; what was recorded before is kept"
                ) from None

    def set_meta(self, **values: JsonValue) -> None:
        """Metadata, written and committed at once."""
        with self._writing() as ours:
            if ours:
                self._con.executemany(META_UPSERT, _meta_rows(values))
                self._con.commit()

    def set_step(self, idx: int, name: str, kind: str, t_start: float, t_end: float | None) -> None:
        """Start (and later end) of a procedure step."""
        with self._writing() as ours:
            if ours:
                self._con.execute(
                    "INSERT OR REPLACE INTO steps VALUES (?, ?, ?, ?, ?)",
                    (idx, name, kind, t_start, t_end),
                )
                self._con.commit()

    def set_result(self, name: str, value: JsonObject) -> None:
        """A named result (calibration, check verdict), JSON-serializable."""
        with self._writing() as ours:
            if ours:
                self._con.execute(
                    "INSERT OR REPLACE INTO results VALUES (?, ?)", (name, json.dumps(value))
                )
                self._con.commit()

    # --- the commit thread ----------------------------------------------------------------------

    def _drain(self) -> int:
        # Taken off the queue under the lock its commit holds: a flush (a step about to read the
        # store) waits for rows the writer thread has taken and not yet committed. Taken outside
        # it, a busy computer descheduled the writer between the two and a step read a store
        # missing them (a linearity axis found 2 settled points of 5, once, in simulated time).
        with self._lock:
            batches: dict[str, list[tuple[Any, ...]]] = {}
            while True:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is None:
                    continue
                batches.setdefault(item[0], []).append(item[1])
            if not batches:
                return 0
            n = sum(len(r) for r in batches.values())
            try:
                if not self._begin_if_ours():
                    self.rows_dropped += n
                    return 0
                for table, rows in batches.items():
                    cols = TABLE_COLUMNS[table]
                    self._con.executemany(
                        f"INSERT INTO {table} ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})",
                        rows,
                    )
                self._con.commit()
            except BaseException:
                if self._con.in_transaction:
                    self._con.rollback()
                raise
            self.rows_written += n
        return n

    def _renew_lease(self) -> None:
        """Tell readers this run is still being recorded (see the module's docstring)."""
        self._lease["seq"] = int(self._lease.get("seq", 0)) + 1
        self._lease["renewed_at"] = time.time()
        with self._lock:
            try:
                if not self._begin_if_ours():
                    return
                self._con.execute(META_UPSERT, ("lease", json.dumps(self._lease)))
                self._con.commit()
            except BaseException:
                if self._con.in_transaction:
                    self._con.rollback()
                raise

    def _run(self) -> None:
        renew_at = time.monotonic() + LEASE_PERIOD_S
        while not self._stop.wait(COMMIT_INTERVAL_S):
            try:
                self._drain()
                if time.monotonic() >= renew_at:
                    self._renew_lease()
                    renew_at = time.monotonic() + LEASE_PERIOD_S
            except sqlite3.Error as exc:  # disk full, I/O error: what is committed stays
                self.error = exc
                return

    def flush(self) -> None:
        """Commit everything queued so far."""
        self._drain()

    def _checkpoint(self) -> None:
        """Fold the WAL into the database file (not in a run another process closed)."""
        if self.closed_by_other is None:
            self._con.execute("PRAGMA wal_checkpoint(TRUNCATE)")

    def close(self, status: str, reason: str) -> list[str]:
        """Commit the rest, record the exit status and reason, close the database and seal the
        run. Never raises on a database error (a full disk): returns what could not be written.
        A run closed by another process (:attr:`closed_by_other`, checked again here) gets
        nothing: neither the rest, nor the status, nor a new seal."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        problems = []
        for what, action in (
            ("the last rows", self._drain),
            (
                "the run's status",
                lambda: self.set_meta(status=status, reason=reason, end_time=run_now()),
            ),
            ("the checkpoint", self._checkpoint),
        ):
            try:
                action()
            except (sqlite3.Error, StoreWriteError) as exc:
                problems.append(f"could not write {what} to {self.path} ({exc})")
        with self._lock:
            self._con.close()
        if self.closed_by_other is not None:
            while True:  # what was queued is not written: count it
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                self.rows_dropped += item is not None
            return problems
        try:
            seal_run(self.folder)
        except (sqlite3.Error, OSError, safe_files.UnsafeFileError) as exc:
            problems.append(f"could not seal the run in {self.folder} ({exc})")
        return problems


@dataclass(frozen=True)
class RunInfo:
    """A stored run as listed by ``rig runs``."""

    run_id: str
    folder: Path
    meta: dict[str, Any]
    closed_now: bool = False
    """Found dead and marked incomplete by this listing (:attr:`RunReader.closed_now`)."""

    @property
    def status(self) -> str:
        """complete, aborted, error, incomplete or running."""
        return str(self.meta.get("status", RunStatus.INCOMPLETE))


class RunReader:
    """Read side of a stored run (opened read-write only to mark a killed run incomplete)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.path = folder / "run.sqlite"
        if not self.path.exists():
            raise UserInputError(
                f"{folder}: not a run folder (no run.sqlite); list runs with 'rig runs'"
            )
        safe_files.check_folder(folder)  # a link (to the folder or run.sqlite) is refused
        safe_files.regular_file(self.path)
        try:
            self._con = _connect(self.path)
            meta = self.meta()
        except sqlite3.DatabaseError as exc:  # truncated or overwritten: one line, exit 2
            with contextlib.suppress(AttributeError, sqlite3.Error):
                self._con.close()
            raise damaged(folder, exc) from None
        self.closed_now = False
        """This reader found the run's recorder gone and marked it incomplete (its outputs may
        still be on: ``rig runs`` switches them off when nobody holds them)."""
        if meta.get("status") == RunStatus.RUNNING:
            reason = _recorder_gone(self._con, meta)
            if reason is not None and self._mark_incomplete(meta.get("lease"), reason):
                self.closed_now = True
                with contextlib.suppress(sqlite3.Error, OSError):
                    seal_run(folder)  # closed now: nobody will write to it again

    def _mark_incomplete(self, lease: Any, reason: str) -> bool:
        """Mark the run incomplete unless it closed or renewed its lease meanwhile (checked in
        the same write transaction); True when it was marked."""
        con = self._con
        con.commit()  # (no transaction of ours is open; BEGIN needs none)
        con.execute("BEGIN IMMEDIATE")
        try:
            now = dict(con.execute("SELECT key, value FROM meta WHERE key IN ('status', 'lease')"))
            if json.loads(now.get("status", "null")) != RunStatus.RUNNING or (
                json.loads(now.get("lease", "null")) != lease
            ):
                con.rollback()
                return False
            con.execute(
                "INSERT OR REPLACE INTO meta VALUES ('status', ?), ('reason', ?)",
                (json.dumps(RunStatus.INCOMPLETE), json.dumps(reason)),
            )
            con.commit()
        except BaseException:
            con.rollback()
            raise
        return True

    def meta(self) -> dict[str, Any]:
        """All metadata."""
        return {k: json.loads(v) for k, v in self._con.execute("SELECT key, value FROM meta")}

    def samples(self, device: str) -> list[tuple[float, float, float, float]]:
        """(t, x, y, z) rows of one magnetometer, in time order."""
        return list(
            self._con.execute(
                "SELECT t, x, y, z FROM samples WHERE device = ? ORDER BY t", (device,)
            )
        )

    def dated_samples(self, device: str) -> list[tuple[float, float, float, float, float]]:
        """(t, x, y, z, t_unc) rows of one magnetometer in the order of :meth:`samples`: the
        sample was taken within t +- t_unc (s; NaN when the run did not record it)."""
        unc = TIME_UNCERTAINTY if self._has_time_uncertainty() else "NULL"
        return [
            (t, x, y, z, math.nan if u is None else u)
            for t, x, y, z, u in self._con.execute(
                f"SELECT t, x, y, z, {unc} FROM samples WHERE device = ? ORDER BY t", (device,)
            )
        ]

    def _has_time_uncertainty(self) -> bool:
        """Whether this run recorded date uncertainties (runs before ADR 0020's did not)."""
        cols = {r[1] for r in self._con.execute("PRAGMA table_info(samples)")}
        return TIME_UNCERTAINTY in cols

    def devices(self) -> list[str]:
        """Magnetometers with samples."""
        return [
            r[0] for r in self._con.execute("SELECT DISTINCT device FROM samples ORDER BY device")
        ]

    def channel(self, name: str) -> list[tuple[float, float | None, float | None]]:
        """(t, commanded, measured) rows of a channel (current A; a thermometer's C)."""
        return list(self._con.execute(
            "SELECT t, commanded, measured FROM channels WHERE channel = ? ORDER BY t", (name,)))  # fmt: skip

    def channel_column(
        self, name: str, column: Literal["commanded", "measured"]
    ) -> list[tuple[float, float]]:
        """(t, value) of a channel's rows that have a ``column`` value, in time order."""
        if column not in ("commanded", "measured"):
            raise ValueError(f"no channel column {column!r}")
        return list(self._con.execute(
            f"SELECT t, {column} FROM channels WHERE channel = ? AND {column} IS NOT NULL"
            " ORDER BY t", (name,)))  # fmt: skip

    def channel_names(self) -> list[str]:
        """Recorded current channels."""
        return [
            r[0]
            for r in self._con.execute("SELECT DISTINCT channel FROM channels ORDER BY channel")
        ]

    def commands(self) -> list[tuple[float, int | None, str, dict[str, Any]]]:
        """(t, step, kind, payload) of every command."""
        return [(t, s, k, json.loads(p)) for t, s, k, p in self._con.execute(
            "SELECT t, step, kind, payload FROM commands ORDER BY t")]  # fmt: skip

    def events(self) -> list[tuple[float, str, str]]:
        """(t, level, message) log events."""
        return list(self._con.execute("SELECT t, level, message FROM events ORDER BY t"))

    def steps(self) -> list[tuple[int, str, str, float, float | None]]:
        """(index, name, kind, t_start, t_end) of each step."""
        return list(
            self._con.execute("SELECT idx, name, kind, t_start, t_end FROM steps ORDER BY idx")
        )

    def results(self) -> dict[str, Any]:
        """Named results."""
        return {k: json.loads(v) for k, v in self._con.execute("SELECT name, value FROM results")}

    def count(self, table: str) -> int:
        """Rows in a table."""
        if table not in ("samples", "channels", "commands", "events", "steps", "results"):
            raise ValueError(table)
        return int(self._con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])

    def close(self) -> None:
        """Close the database."""
        self._con.close()


def _owner_alive(pid: Any) -> bool:
    from rig.child_process import process_alive

    return isinstance(pid, int) and pid > 0 and process_alive(pid)


KILLED = "the rig process ended without closing the run (killed?)"


def _lease_of(con: sqlite3.Connection) -> dict[str, Any]:
    """This process's lease of the run in ``con``, continuing the count of the one stored."""
    row = con.execute("SELECT value FROM meta WHERE key = 'lease'").fetchone()
    old = json.loads(row[0]) if row else {}
    seq = old.get("seq") if isinstance(old, dict) else None
    return {**host_identity.identity(), "seq": seq if isinstance(seq, int) else 0,
            "period_s": LEASE_PERIOD_S, "expiry_s": LEASE_EXPIRY_S}  # fmt: skip


def _recorder_gone(con: sqlite3.Connection, meta: dict[str, Any]) -> str | None:
    """Why the recorder of a ``running`` run is gone (the reason to record), None while it may
    be recording (by PID in its own boot and PID namespace, else by its lease) or while its
    guardian is provably alive (it switches the outputs off, records what it did and closes the
    run itself: a reader closing it first would leave its record out of the sealed run)."""
    gone = _recorder_gone_by_lease(con, meta)
    if gone is not None and host_identity.alive(meta.get("guardian")) is True:
        return None
    return gone


def _recorder_gone_by_lease(con: sqlite3.Connection, meta: dict[str, Any]) -> str | None:
    """:func:`_recorder_gone`, the recorder alone."""
    lease = meta.get("lease")
    if not isinstance(lease, dict):  # recorded before leases: its PID, as then
        return None if _owner_alive(meta.get("pid")) else KILLED
    alive = host_identity.alive(lease)
    if alive is not None:
        return None if alive else KILLED
    if not lease_expired(con, lease):
        return None
    when = lease.get("renewed_at")
    at = (
        dt.datetime.fromtimestamp(when, dt.UTC).isoformat(timespec="seconds")
        if isinstance(when, int | float) and not isinstance(when, bool) and abs(when) < 1e11
        else "?"
    )
    return (
        f"the rig process on {lease.get('host', '?')} stopped renewing its lease (last at {at})"
        " without closing the run (killed?)"
    )


def lease_expired(con: sqlite3.Connection, lease: dict[str, Any]) -> bool:
    """Has the recorder of ``lease`` (the stored ``lease`` row of ``con``) stopped renewing it?
    No when its wall-clock time is within :data:`LEASE_EXPIRY_S` of ours; otherwise (a dead
    recorder, or hosts whose clocks disagree) yes unless the row changes within
    :data:`LEASE_WATCH_S`."""
    when = lease.get("renewed_at")
    if (
        isinstance(when, int | float)
        and not isinstance(when, bool)
        and abs(time.time() - when) <= LEASE_EXPIRY_S
    ):
        return False
    deadline = time.monotonic() + LEASE_WATCH_S
    while time.monotonic() < deadline:
        time.sleep(0.1)
        row = con.execute("SELECT value FROM meta WHERE key = 'lease'").fetchone()
        if row is None or json.loads(row[0]) != lease:
            return False  # renewed (or rewritten): someone is recording it
    return True


def new_run(runs_dir: Path, label: str, **meta: Any) -> RunWriter:
    """Create ``<runs_dir>/<date>-<time>-<label>/`` with a fresh store marked running."""
    import os
    import re

    safe_label = re.sub(r"[^A-Za-z0-9_.-]+", "-", label).strip("-") or "run"
    started = timebase.wall_time()  # the run's date, on its clock (the lease's is the wall's)
    stamp = dt.datetime.fromtimestamp(started, dt.UTC).strftime("%Y%m%d-%H%M%S")
    folder = runs_dir / f"{stamp}-{safe_label}"
    n = 1
    while folder.exists():
        n += 1
        folder = runs_dir / f"{stamp}-{safe_label}-{n}"
    try:
        folder.mkdir(parents=True)
    except OSError as exc:
        raise UserInputError(
            f"cannot create the run folder {folder}: {exc.strerror}; check --runs-dir"
        ) from None
    # Built under another name and renamed: a reader never sees a run.sqlite without its tables.
    tmp = folder / ".run.sqlite.new"
    con = _connect(tmp)
    try:
        con.executescript(SCHEMA)
        con.executemany(META_UPSERT, _meta_rows(dict(
            run_id=folder.name, status=RunStatus.RUNNING, pid=os.getpid(),
            lease={**host_identity.identity(), "seq": 0, "renewed_at": time.time(),
                   "period_s": LEASE_PERIOD_S, "expiry_s": LEASE_EXPIRY_S},
            # the same instant on both of the run's clocks: exports convert sample times to UTC
            start_time=dt.datetime.fromtimestamp(started, dt.UTC).isoformat(timespec="milliseconds"),
            start_monotonic=timebase.monotonic(),
            clock="simulated" if timebase.is_simulated() else "wall", **meta)))  # fmt: skip
        con.commit()
    finally:
        con.close()
    os.replace(tmp, folder / "run.sqlite")
    return RunWriter(folder)


def list_runs(runs_dir: Path) -> list[RunInfo]:
    """Every run folder under ``runs_dir``, newest first; one that cannot be read (a damaged
    ``run.sqlite``, a link) is listed with status ``damaged`` and the reason."""
    out: list[RunInfo] = []
    if not runs_dir.exists():
        return out
    for folder in sorted(runs_dir.iterdir(), reverse=True):
        if (folder / "run.sqlite").exists():
            try:
                reader = RunReader(folder)
            except (UserInputError, safe_files.UnsafeFileError) as exc:
                out.append(RunInfo(folder.name, folder, {"status": "damaged", "reason": str(exc)}))
                continue
            out.append(RunInfo(folder.name, folder, reader.meta(), reader.closed_now))
            reader.close()
    return out
