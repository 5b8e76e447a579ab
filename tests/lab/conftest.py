"""A real PostgreSQL server for the lab index tests (Debian's postgresql package; never a mock).

Without the server binaries the tests skip, unless RIG_REQUIRE_TOOLS is set (``.ci/run``): then
they fail (tests.tools).
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator

import pytest

from bench.labfixture import PgServer, pg_server, postgres_bin
from tests.tools import require_tool

_dbs = itertools.count(1)


@pytest.fixture(scope="session")
def pg() -> Iterator[PgServer]:
    """One throwaway cluster for the session, stopped at its end."""
    require_tool("postgresql", postgres_bin(), what="the lab index tests (its server binaries)")
    with pg_server() as server:
        yield server


@pytest.fixture
def lab_url(pg: PgServer) -> str:
    """A fresh, empty database owned by ``rig``; its URL (no password: PGPASSWORD is set)."""
    name = f"lab_{os.getpid()}_{next(_dbs)}"
    pg.psql(f"CREATE DATABASE {name} OWNER rig", db="postgres")
    return pg.url.rsplit("/", 1)[0] + f"/{name}"


@pytest.fixture(autouse=True)
def _password(monkeypatch: pytest.MonkeyPatch) -> None:
    """The role's password through libpq's own PGPASSWORD (children inherit it)."""
    from bench.labfixture import PASSWORD

    monkeypatch.setenv("PGPASSWORD", PASSWORD)
    monkeypatch.delenv("RIG_LAB_URL", raising=False)
