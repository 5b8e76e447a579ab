"""The run's acceptance verdict as it is stored: each criterion judged and the overall PASS, FAIL
or RE-RUN. The ``check`` step kind writes it (:mod:`rig.steps.check`); the engine, the report,
the page, the lab index and the CLI read it here, never through the step kind."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from rig import stored
from rig.errors import StoredResultError
from rig.store.run_states import Verdict

VERDICT_RESULT = "verdict"
"""The name the check step stores its verdict under (the last check's verdict is the run's)."""


def _verdict(d: Mapping[str, Any], key: str, what: str) -> Verdict:
    value = stored.text(d, key, what)
    try:
        return Verdict(value)
    except ValueError:
        raise StoredResultError(
            f"stored {what}: '{key}' must be one of {', '.join(Verdict)}, got {value!r:.80}"
        ) from None


@dataclass(frozen=True)
class CriterionResult:
    """One acceptance criterion judged: its value (in ``unit``) against its limits, the margin to
    the nearer limit (same unit; negative: beyond it) and PASS or FAIL; or, when its value could not
    be read, FAIL and the reason."""

    name: str
    verdict: Verdict
    value: float | None = None
    """None: the value could not be read (``reason`` says why)."""
    unit: str | None = None
    """The value's unit ("" for a ratio); None in rows recorded before rows carried their unit."""
    min: float | None = None
    max: float | None = None
    margin: float | None = None
    reason: str = ""
    uncertainty: float | None = None
    """The value's expanded uncertainty (k = 2, same unit) when its result has a budget: the
    margin is then what is left beyond it (guarded acceptance)."""

    def to_dict(self) -> dict[str, Any]:
        """The stored row."""
        if self.value is None:
            return {"name": self.name, "verdict": self.verdict, "reason": self.reason}
        unit = {} if self.unit is None else {"unit": self.unit}
        u = {} if self.uncertainty is None else {"uncertainty": self.uncertainty}
        return {"name": self.name, "value": self.value, **unit, **u, "min": self.min,
                "max": self.max, "margin": self.margin, "verdict": self.verdict}  # fmt: skip

    @classmethod
    def from_dict(cls, d: Any) -> CriterionResult:
        """Read a stored row; a :class:`StoredResultError` names what is wrong."""
        what = "check criterion"
        d = stored.mapping(d, what)
        name = stored.text(d, "name", what)
        what = f"check criterion '{name}'"
        verdict = _verdict(d, "verdict", what)
        if "value" not in d:
            return cls(name, verdict, reason=stored.text(d, "reason", what))
        unit = None if "unit" not in d else stored.text(d, "unit", what)
        return cls(name, verdict, stored.number(d, "value", what), unit,
                   stored.optional_number(d, "min", what), stored.optional_number(d, "max", what),
                   stored.optional_number(d, "margin", what), "",
                   stored.optional_number(d, "uncertainty", what))  # fmt: skip


@dataclass(frozen=True)
class CheckVerdict:
    """The check step's verdict: each criterion judged and the overall PASS, FAIL or RE-RUN (the
    data of a judged result failed the timing checks: ``rerun`` names them and why)."""

    criteria: tuple[CriterionResult, ...]
    overall: Verdict
    rerun: tuple[tuple[str, str], ...] = ()
    """(result name, why) of each judged result whose data failed the timing checks."""

    @property
    def failed(self) -> list[str]:
        """The names of the criteria not passed."""
        return [c.name for c in self.criteria if c.verdict != Verdict.PASS]

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping (``rerun`` only when there is one)."""
        out: dict[str, Any] = {"criteria": [c.to_dict() for c in self.criteria],
                               "overall": self.overall}  # fmt: skip
        if self.rerun:
            out["rerun"] = [{"result": r, "why": why} for r, why in self.rerun]
        return out

    @classmethod
    def from_dict(cls, d: Any) -> CheckVerdict:
        """Read a stored verdict; a :class:`StoredResultError` names what is wrong."""
        what = "check verdict"
        d = stored.mapping(d, what)
        rows = stored.entry(d, "criteria", what)
        if not isinstance(rows, list):
            raise StoredResultError(f"stored {what}: 'criteria' must be a list, got {rows!r:.80}")
        rerun = stored.entry(d, "rerun", what) if "rerun" in d else []
        if not isinstance(rerun, list):
            raise StoredResultError(f"stored {what}: 'rerun' must be a list, got {rerun!r:.80}")
        notes = [stored.mapping(r, f"{what} rerun entry") for r in rerun]
        return cls(
            tuple(CriterionResult.from_dict(r) for r in rows),
            _verdict(d, "overall", what),
            tuple((stored.text(n, "result", what), stored.text(n, "why", what)) for n in notes),
        )


def check_verdict(results: Mapping[str, Any]) -> CheckVerdict | None:
    """The run's verdict (the last check step's), None when no check has judged yet; a malformed
    stored verdict is a :class:`StoredResultError`. The one lookup of 'the check verdict'."""
    if VERDICT_RESULT not in results:
        return None
    return CheckVerdict.from_dict(results[VERDICT_RESULT])
