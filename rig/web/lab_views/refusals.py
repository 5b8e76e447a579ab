"""``/lab/refusals``: the runs a sync refused (``lab_refusals``: changed since they were sealed,
or not storable), most recently refused first, with how often and why (``rig lab audit`` lists
them too)."""

from __future__ import annotations

from typing import Any

from rig.lab.queries import refusals
from rig.web.lab_views.view import LabView, Params, with_index

REFUSAL_COLUMNS = ["run_id", "rig", "host", "kind", "last_at", "first_at", "attempts", "reason",
                   "sealed_sha256"]  # fmt: skip


def lab_refusals(url: str) -> dict[str, Any]:
    """Every refusal the index recorded."""
    rows = with_index(url, refusals)
    return {"title": "Runs the lab index refused",
            "tables": [("changed since sealed, or not storable; attempts: syncs that refused it",
                        REFUSAL_COLUMNS, rows)]}  # fmt: skip


def _load(url: str, q: Params) -> dict[str, Any]:
    return lab_refusals(url)


VIEW = LabView("refusals", "Refusals", _load)
