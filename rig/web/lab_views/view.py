"""The contract of a lab view on the page (``rig serve --lab URL``): ``/lab/<name>``.

A view is one module in this package with ``VIEW = LabView(...)`` and one line in
:data:`rig.web.lab_views.VIEWS`. Its ``load(url, params)`` runs in a worker thread with its own
connection to the index (the index is a server shared by many rigs; a page holds nothing open, and
a slow database never blocks the live views) and returns the page's data: ``title`` and
``tables`` (caption, columns or ``[]`` for every column of the rows, rows), or ``None`` for the
view's form without results. A :class:`~rig.errors.RigError` (the index is down or refused) is
shown as one line with status 503.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

from rig.lab.schema import open_index

Params = Mapping[str, str]
"""The request's query parameters and path parameters (``serial`` on a DUT's page)."""
T = TypeVar("T")


@dataclass(frozen=True)
class LabView:
    """One view: ``name`` (its path ``/lab/<name>``), ``tab`` (its link in the lab tabs; ``None``
    for a view reached by links only), ``load(url, params)`` (see the module)."""

    name: str
    tab: str | None
    load: Callable[[str, Params], dict[str, Any] | None]


def with_index(url: str, query: Callable[[Any], T]) -> T:
    """``query(conn)`` on a connection of its own to the index at ``url``, closed after."""
    conn = open_index(url)
    try:
        return query(conn)
    finally:
        conn.close()
