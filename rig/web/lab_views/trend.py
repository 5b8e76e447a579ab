"""``/lab/trend?param=&lot=``: a calibration parameter over runs with each lot's control limits
(its plot is ``/lab/trend.png`` with the same query)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rig.lab.queries import trend
from rig.web.lab_views.view import LabView, Params, with_index

TREND_COLUMNS = ["run_id", "rig", "lot", "dut_serial", "started_at", "value", "sigma", "outlier"]


def lab_trend(url: str, param: str, lot: str | None, png: Path | None = None) -> dict[str, Any]:
    """A calibration parameter over runs with each lot's control limits (and its plot to ``png``)."""
    tr = with_index(url, lambda c: trend(c, param, lot=lot or None))
    if png is not None and tr.rows:
        from rig.lab.plot import trend_png

        trend_png(tr, png)
    limits = [{"lot": name, **lim} for name, lim in sorted(tr.limits.items())]
    return {"title": f"Trend of {param}" + (f" in lot {lot}" if lot else ""),
            "tables": [("control limits (mean +- 3 sigma of the lot)",
                        ["lot", "n", "mean", "sd", "lcl", "ucl"], limits),
                       ("values", TREND_COLUMNS, tr.rows)],
            "found": bool(tr.rows)}  # fmt: skip


def _load(url: str, q: Params) -> dict[str, Any] | None:
    return lab_trend(url, q["param"], q.get("lot")) if q.get("param") else None


VIEW = LabView("trend", "Trend", _load)
