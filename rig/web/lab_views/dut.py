"""``/lab/dut/SERIAL``: every acceptance of one DUT serial (reached from a serial's link)."""

from __future__ import annotations

from typing import Any

from rig.lab.queries import dut
from rig.web.lab_views.view import LabView, with_index

DUT_COLUMNS = ["run_id", "rig", "started_at", "procedure", "status", "verdict", "failed_criteria",
               "min_margin", "operator"]  # fmt: skip


def lab_dut(url: str, serial: str) -> dict[str, Any]:
    """Every acceptance of one DUT serial."""
    rows = with_index(url, lambda c: dut(c, serial))
    return {"title": f"Every run of DUT {serial}", "tables": [("", DUT_COLUMNS, rows)]}


VIEW = LabView("dut", None, lambda url, q: lab_dut(url, q["serial"]))
