"""``/lab/audit``: expired certificates, unsealed runs, and the rigs ranked by their outliers."""

from __future__ import annotations

from typing import Any

from rig.lab.queries import audit
from rig.web.lab_views.view import LabView, Params, with_index


def lab_audit(url: str) -> dict[str, Any]:
    """Expired certificates, unsealed runs, and the rigs ranked by their outliers."""
    found = with_index(url, audit)
    return {"title": "Lab audit", "tables": [
        ("runs with an expired instrument certificate", [], found["expired_certificates"]),
        ("runs without a seal (no data hash)", [], found["unsealed"]),
        ("per rig: failed criteria and values outside their lot's control limits", [],
         found["rigs"]),
    ]}  # fmt: skip


def _load(url: str, q: Params) -> dict[str, Any]:
    return lab_audit(url)


VIEW = LabView("audit", "Audit", _load)
