"""The lab index on the page (``rig serve --lab URL``): the same views as ``rig lab``.

Every view, by name: the one place a new one is registered (ADR 0022). To add one, write a module
here with ``VIEW = LabView(...)`` (:mod:`.view`) and add it to the tuple below; its tab appears in
the lab tabs, its page at ``/lab/<name>`` (docs/architecture.md).
"""

from __future__ import annotations

from rig.web.lab_views import audit, dut, refusals, runs, trend
from rig.web.lab_views.view import LabView

VIEWS: dict[str, LabView] = {m.VIEW.name: m.VIEW for m in (runs, trend, audit, refusals, dut)}
"""Every lab view, in the order of the tabs."""


def tabs() -> list[tuple[str, str]]:
    """``(href, tab)`` of every view with a tab, in order (the runs view is ``/lab``)."""
    return [("/lab" if v.name == "runs" else f"/lab/{v.name}", v.tab) for v in VIEWS.values()
            if v.tab]  # fmt: skip
