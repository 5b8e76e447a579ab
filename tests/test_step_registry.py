"""The step-kind registry is the one place kinds are known: the language, planner, runner and
analysis name no kind, and the technician guide documents every kind and parameter."""

from __future__ import annotations

import re
from pathlib import Path

from rig.steps import KINDS, field_kinds

ROOT = Path(__file__).resolve().parents[1]
GENERIC = ["rig/procedure/language.py", "rig/procedure/plan.py", "rig/analysis.py",
           *(str(p.relative_to(ROOT)) for p in sorted((ROOT / "rig/engine").glob("*.py"))),
           *(str(p.relative_to(ROOT)) for p in sorted((ROOT / "rig/report").glob("*.py"))),
           *(str(p.relative_to(ROOT)) for p in sorted((ROOT / "rig/web").rglob("*.py"))),
           "rig/web/static/app.js"]  # fmt: skip
"""Every engine, report and page module: none of them may name a step kind."""
NOT_A_KIND = {"prompt"}
"""Words that are a step kind's name and also the page's operator-prompt channel (a JSON key of
the live state and the page), which every module may name."""


def test_generic_modules_name_no_step_kind() -> None:
    for rel in GENERIC:
        text = (ROOT / rel).read_text()
        named = [k for k in KINDS if k not in NOT_A_KIND and re.search(rf"[\"']{k}[\"']", text)]
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


def test_every_module_that_defines_a_kind_is_registered_and_named_once() -> None:
    """A step module whose registry line is forgotten is named with the fix (before: a bare
    KeyError in a test fake); the registry names each module once."""
    from rig.steps import STEP_MODULES

    defining = sorted(p.stem for p in (ROOT / "rig/steps").glob("*.py")
                      if re.search(r"^KIND = ", p.read_text(), re.MULTILINE))  # fmt: skip
    missing = [f"rig/steps/{m}.py" for m in defining if m not in STEP_MODULES]
    assert not missing, (
        f"{', '.join(missing)} defines a step kind (KIND) that is not registered: add its module"
        " name to STEP_MODULES in rig/steps/__init__.py"
    )
    assert len(set(STEP_MODULES)) == len(STEP_MODULES) == len(KINDS) == len(defining)
