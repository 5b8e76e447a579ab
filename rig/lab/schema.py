"""Connecting to the lab index and keeping its schema at the newest migration.

The schema is alembic's (``rig/lab/migrations``). :func:`ensure_schema` checks the version with one
query and runs ``alembic upgrade head`` only when it is behind, holding a PostgreSQL advisory lock
so rig processes that start at once migrate one after the other (the others then find it done).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from rig.errors import RigError
from rig.lab.url import masked

if TYPE_CHECKING:
    import psycopg

HEAD = "0002"
"""The newest migration (``migrations/versions``): the schema this code reads and writes."""
MIGRATION_LOCK = 0x716C6162  # "qlab": the advisory lock key serializing migrations
MIGRATIONS = Path(__file__).resolve().parent / "migrations"


class LabUnavailableError(RigError):
    """The lab index cannot be reached or refused us; the run folders are untouched."""


def unavailable(url: str, exc: BaseException) -> LabUnavailableError:
    """One line: which index (password masked), PostgreSQL's reason, and what to do."""
    reason = masked(str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__)
    return LabUnavailableError(
        f"the lab index {masked(url)} is not available ({reason}); the runs stay in their"
        " folders: run 'rig lab sync' again once it is up (see docs/lab.md)"
    )


def connect(
    url: str, *, timeout_s: float = 10.0, statement_timeout_s: float | None = None
) -> psycopg.Connection[Any]:
    """A connection (not autocommit); :class:`LabUnavailableError` when the server cannot be reached
    or refuses the login. Credentials come from the URL, PGPASSWORD or ~/.pgpass (libpq's own).
    ``statement_timeout_s``: the session's ``statement_timeout``, and ``lock_timeout`` at 90% of
    it (a statement waiting longer for the server, or for a lock, is cancelled: the error says
    which)."""
    import psycopg

    try:
        conn = psycopg.connect(url, connect_timeout=max(2, round(timeout_s)))
    except psycopg.Error as exc:
        raise unavailable(url, exc) from None
    if statement_timeout_s is not None:
        ms = max(1, round(1000 * statement_timeout_s))
        try:
            with conn.cursor() as cur:
                cur.execute("SELECT set_config('statement_timeout', %s, false),"
                            " set_config('lock_timeout', %s, false)",
                            (str(ms), str(max(1, round(0.9 * ms)))))  # fmt: skip
            conn.commit()
        except psycopg.Error as exc:
            conn.close()
            raise unavailable(url, exc) from None
    return conn


def open_index(
    url: str, *, timeout_s: float = 10.0, statement_timeout_s: float | None = None
) -> psycopg.Connection[Any]:
    """A connection at the newest schema (migrated if behind); :class:`LabUnavailableError` when
    the server cannot be reached or refuses. The caller closes it. ``statement_timeout_s``: see
    :func:`connect`."""
    import psycopg

    conn = connect(url, timeout_s=timeout_s, statement_timeout_s=statement_timeout_s)
    try:
        ensure_schema(conn)
    except psycopg.Error as exc:
        conn.close()
        raise unavailable(url, exc) from None
    except BaseException:
        conn.close()
        raise
    return conn


def schema_version(conn: psycopg.Connection[Any]) -> str | None:
    """alembic's version of the index, None on an empty database."""
    with conn.cursor() as cur:
        cur.execute("SELECT to_regclass('alembic_version') IS NOT NULL")
        row = cur.fetchone()
        if not row or not row[0]:
            conn.rollback()
            return None
        cur.execute("SELECT version_num FROM alembic_version")
        version = cur.fetchone()
    conn.rollback()
    return str(version[0]) if version else None


def ensure_schema(conn: psycopg.Connection[Any]) -> None:
    """Bring the schema to :data:`HEAD` (no-op when it is there), one process at a time."""
    if schema_version(conn) == HEAD:
        return
    with conn.cursor() as cur:
        cur.execute("SELECT pg_advisory_lock(%s)", (MIGRATION_LOCK,))
    conn.commit()
    try:
        if schema_version(conn) != HEAD:  # another process may have migrated while we waited
            _upgrade(conn)
    finally:
        with conn.cursor() as cur:
            cur.execute("SELECT pg_advisory_unlock(%s)", (MIGRATION_LOCK,))
        conn.commit()


def _upgrade(conn: psycopg.Connection[Any]) -> None:
    """``alembic upgrade head`` on a connection of its own (SQLAlchemy over psycopg)."""
    import sqlalchemy
    from alembic import command
    from alembic.config import Config

    dsn = conn.info.dsn
    password = conn.info.password
    import psycopg

    def creator() -> Any:
        return psycopg.connect(dsn, password=password) if password else psycopg.connect(dsn)

    engine = sqlalchemy.create_engine(
        "postgresql+psycopg://", creator=creator, poolclass=sqlalchemy.pool.NullPool
    )
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    try:
        with engine.begin() as sa_conn:
            cfg.attributes["connection"] = sa_conn
            command.upgrade(cfg, "head")
    finally:
        engine.dispose()
