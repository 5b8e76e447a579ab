"""``/lab`` (and ``/lab/runs``): the newest runs of every rig, filtered by ``dut`` and ``status``,
at most ``limit`` (100 unless given, 1 to 1000)."""

from __future__ import annotations

from typing import Any

from rig.lab.queries import runs
from rig.web.lab_views.view import LabView, Params, with_index

RUN_COLUMNS = ["run_id", "rig", "started_at", "procedure", "dut_serial", "lot", "operator",
               "status", "verdict"]  # fmt: skip


def lab_runs(url: str, dut_serial: str | None, status: str | None, limit: int) -> dict[str, Any]:
    """The newest runs of every rig (filtered)."""
    rows = with_index(url, lambda c: runs(c, dut=dut_serial or None, status=status or None,
                                          limit=limit))  # fmt: skip
    return {"title": "Lab index: runs of every rig", "tables": [("", RUN_COLUMNS, rows)]}


def _load(url: str, q: Params) -> dict[str, Any]:
    limit = int(q["limit"]) if q.get("limit", "").isdigit() else 100
    return lab_runs(url, q.get("dut"), q.get("status"), max(1, min(limit, 1000)))


VIEW = LabView("runs", "Runs", _load)
