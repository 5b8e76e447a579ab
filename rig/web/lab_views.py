"""The lab index on the page (``rig serve --lab URL``): the same views as ``rig lab``.

Each request opens its own connection (the index is a server shared by many rigs; a page holds
nothing open) and runs in a worker thread, so a slow database never blocks the live views.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rig.lab.queries import audit, dut, runs, trend
from rig.lab.schema import open_index

RUN_COLUMNS = ["run_id", "rig", "started_at", "procedure", "dut_serial", "lot", "operator",
               "status", "verdict"]  # fmt: skip
DUT_COLUMNS = ["run_id", "rig", "started_at", "procedure", "status", "verdict", "failed_criteria",
               "min_margin", "operator"]  # fmt: skip
TREND_COLUMNS = ["run_id", "rig", "lot", "dut_serial", "started_at", "value", "sigma", "outlier"]


def lab_runs(url: str, dut_serial: str | None, status: str | None, limit: int) -> dict[str, Any]:
    """The newest runs of every rig (filtered)."""
    conn = open_index(url)
    try:
        rows = runs(conn, dut=dut_serial or None, status=status or None, limit=limit)
    finally:
        conn.close()
    return {"title": "Lab index: runs of every rig",
            "tables": [("", RUN_COLUMNS, rows)]}  # fmt: skip


def lab_dut(url: str, serial: str) -> dict[str, Any]:
    """Every acceptance of one DUT serial."""
    conn = open_index(url)
    try:
        rows = dut(conn, serial)
    finally:
        conn.close()
    return {"title": f"Every run of DUT {serial}", "tables": [("", DUT_COLUMNS, rows)]}


def lab_trend(url: str, param: str, lot: str | None, png: Path | None = None) -> dict[str, Any]:
    """A calibration parameter over runs with each lot's control limits (and its plot to ``png``)."""
    conn = open_index(url)
    try:
        tr = trend(conn, param, lot=lot or None)
    finally:
        conn.close()
    if png is not None and tr.rows:
        from rig.lab.plot import trend_png

        trend_png(tr, png)
    limits = [{"lot": name, **lim} for name, lim in sorted(tr.limits.items())]
    return {"title": f"Trend of {param}" + (f" in lot {lot}" if lot else ""),
            "tables": [("control limits (mean +- 3 sigma of the lot)",
                        ["lot", "n", "mean", "sd", "lcl", "ucl"], limits),
                       ("values", TREND_COLUMNS, tr.rows)],
            "found": bool(tr.rows)}  # fmt: skip


def lab_audit(url: str) -> dict[str, Any]:
    """Expired certificates, unsealed runs, and the rigs ranked by their outliers."""
    conn = open_index(url)
    try:
        found = audit(conn)
    finally:
        conn.close()
    return {"title": "Lab audit", "tables": [
        ("runs with an expired instrument certificate", [], found["expired_certificates"]),
        ("runs without a seal (no data hash)", [], found["unsealed"]),
        ("per rig: failed criteria and values outside their lot's control limits", [],
         found["rigs"]),
    ]}  # fmt: skip
