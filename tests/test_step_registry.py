"""The step-kind registry is the one place kinds are known: the language, planner, runner and
analysis name no kind, and the technician guide documents every kind and parameter."""

from __future__ import annotations

import re
from pathlib import Path

from rig.steps import KINDS, field_kinds

ROOT = Path(__file__).resolve().parents[1]
GENERIC = ["rig/procedure/language.py", "rig/procedure/plan.py", "rig/engine/runner.py",
           "rig/analysis.py", "rig/engine/live.py", "rig/report/acceptance.py",
           "rig/report/sections.py", "rig/report/calibration_figures.py", "rig/report/model.py",
           "rig/report/pdf.py"]  # fmt: skip


def test_generic_modules_name_no_step_kind() -> None:
    for rel in GENERIC:
        text = (ROOT / rel).read_text()
        named = [k for k in KINDS if re.search(rf"[\"']{k}[\"']", text)]
        assert not named, f"{rel} names step kinds {named}: move that knowledge into rig/steps/"


def test_the_guide_documents_every_kind_and_parameter() -> None:
    guide = (ROOT / "docs/procedures.md").read_text()
    rows = {m[1]: m[2] for m in re.finditer(r"^\| `(\w+)` \| (.*) \|$", guide, re.M)}
    for name, kind in KINDS.items():
        assert name in rows, f"docs/procedures.md has no row for step '{name}'"
        missing = [p for p in kind.params if p != "text" and f"`{p}" not in rows[name]]
        assert not missing, f"docs/procedures.md: '{name}' lacks {missing}"


def test_field_kinds_are_those_that_take_loads() -> None:
    assert {
        "null_field",
        "sphere_sweep",
        "orbit_replay",
        "noise_spectrum",
        "linearity",
    } <= field_kinds()
    assert not {"prompt", "calibrate", "check", "report", "characterize_cage"} & field_kinds()
