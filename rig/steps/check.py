"""``check``: acceptance criteria on the results so far; the run's verdict."""

from __future__ import annotations

from collections.abc import Sequence
from fnmatch import fnmatchcase
from typing import Any, ClassVar

from rig.analysis import evaluate_criteria
from rig.steps.base import StepExecution, StepKind
from rig.steps.vocabulary import (
    NOT_FINITE_FIX,
    NotFiniteError,
    ProcedureError,
    Step,
    StepParam,
    finite_number,
    suggest,
)
from rig.store.run_states import Verdict
from rig.verdict import VERDICT_RESULT, CheckVerdict

CRITERION_KEYS = {"result", "value", "min", "max", "name", "__line__"}


class Check(StepKind):
    name = "check"
    summary = "acceptance criteria on the results: PASS/FAIL with margins"
    params: ClassVar[dict[str, StepParam]] = {"criteria": StepParam("list_dict", required=True)}

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        path = where.split(":", 1)[0]
        for c in params["criteria"]:
            bad = set(c) - CRITERION_KEYS
            at = f"{path}:{c['__line__']}: {where.split(': ', 1)[1]}" if "__line__" in c else where
            if bad or "result" not in c or "value" not in c or ("min" not in c and "max" not in c):
                raise ProcedureError(
                    f"{at}: a criterion needs result, value and min and/or max{f'; unknown {sorted(bad)}' if bad else ''}"
                )
            for key in ("min", "max"):
                if c.get(key) is not None:
                    c[key] = _limit(c[key], key, at)

    def execution(self, ctx: Any, step: Any) -> StepExecution:
        return Judge(ctx, step)

    def check_against(self, step: Step, earlier: Sequence[Step]) -> None:
        """Each criterion names a step before this one and a value that step's kind records
        (its ``result_values``), or the procedure is refused with the valid names."""
        from rig.steps import KINDS

        by_name = {s.name: s for s in earlier}
        for c in step.params["criteria"]:
            at = f"{step.where.path}:{c.get('__line__', step.where.line)}: step {step.index + 1} (check)"
            what = f"criterion '{c.get('name') or c['result']}'"
            source = by_name.get(str(c["result"]))
            if source is None:
                raise ProcedureError(
                    f"{at}: {what}: no step named '{c['result']}' before it"
                    f"{suggest(str(c['result']), by_name)} (steps before it:"
                    f" {', '.join(by_name) or 'none'})"
                )
            values = KINDS[source.kind].result_values
            if values is None or any(fnmatchcase(str(c["value"]), v) for v in values):
                continue
            records = ", ".join(values) or "no result"
            literal = [v for v in values if "*" not in v]
            raise ProcedureError(
                f"{at}: {what}: step '{source.name}' ({source.kind}) records no"
                f" '{c['value']}'{suggest(str(c['value']), literal)}; it records: {records}"
                + (" (* stands for any name)" if len(literal) < len(values) else "")
            )


def _limit(value: Any, key: str, at: str) -> int | float:
    """A criterion's ``min`` or ``max``: a finite number (text from a ``{parameter}`` converted)."""
    number = value
    if isinstance(value, str):
        try:
            number = float(value)
        except ValueError:
            number = None
    if isinstance(number, bool) or not isinstance(number, int | float):
        raise ProcedureError(f"{at}: a criterion's '{key}' must be a number, got {value!r}")
    if finite_number(number) is None:
        raise NotFiniteError(
            f"{at}: a criterion's '{key}' must be a finite number, got {value!r}; {NOT_FINITE_FIX}"
        )
    return number


class Judge(StepExecution):
    def run(self, payload: dict[str, Any]) -> None:
        verdict = CheckVerdict.from_dict(evaluate_criteria(self.ctx.results, payload["criteria"]))
        self.ctx.record_result(VERDICT_RESULT, verdict.to_dict())
        for row in verdict.criteria:
            level = "info" if row.verdict == Verdict.PASS else "warning"
            self.ctx.event(level, f"check {row.name}: {row.verdict}")


KIND = Check()
