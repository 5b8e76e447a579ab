"""The fake run context offers everything the real contract does, so a step that passes its unit
tests uses nothing the runner lacks."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

from rig.steps import KINDS
from rig.steps.base import RunContext
from rig.store.run_store import RunReader
from tests.steps.fake_context import FakeContext, FakeReader, make_procedure, make_step


def test_every_kind_has_unit_tests_here() -> None:
    here = "\n".join(p.read_text() for p in Path(__file__).parent.glob("test_*.py"))
    untested = [k for k in KINDS if not re.search(rf'make_step\(\s*"{k}"', here)]
    assert not untested, f"step kinds without unit tests in tests/steps: {untested}"


def test_the_fake_context_has_every_member_of_the_contract(tmp_path: Path) -> None:
    ctx = FakeContext(make_procedure(make_step("report")), tmp_path)
    members = (
        set(RunContext.__annotations__)
        | {n for n, v in vars(RunContext).items() if not n.startswith("_") and callable(v)}
        | {"folder"}
    )
    missing = [m for m in sorted(members) if not hasattr(ctx, m)]
    assert not missing, f"FakeContext lacks {missing} of rig.steps.base.RunContext"
    for name, fn in vars(RunContext).items():
        if callable(fn) and not name.startswith("_"):
            want = list(inspect.signature(fn).parameters)[1:]
            have = list(inspect.signature(getattr(ctx, name)).parameters)
            assert have == want, f"FakeContext.{name}{have} differs from RunContext's {want}"


def test_the_fake_reader_reads_like_the_run_store() -> None:
    for name, fn in vars(FakeReader).items():
        if name.startswith("_"):
            continue
        real = getattr(RunReader, name, None)
        assert real is not None, f"FakeReader.{name}: RunReader has no such method"
        assert list(inspect.signature(fn).parameters) == list(inspect.signature(real).parameters), (
            f"FakeReader.{name} takes other arguments than RunReader.{name}"
        )
