"""``prompt``: ask the operator; a "no" aborts the run."""

from __future__ import annotations

from typing import Any, ClassVar

from rig.steps.base import StepExecution, StepKind, ask_or_abort
from rig.steps.vocabulary import StepParam


class Prompt(StepKind):
    name = "prompt"
    summary = "ask the operator to confirm (a 'no' aborts the run)"
    asks_operator = True
    params: ClassVar[dict[str, StepParam]] = {"text": StepParam("str", required=True, text="free")}

    def shorthand(self, body: Any) -> Any:
        return {"text": body} if isinstance(body, str) else body

    def execution(self, ctx: Any, step: Any) -> StepExecution:
        return Ask(ctx, step)


class Ask(StepExecution):
    def run(self, payload: dict[str, Any]) -> None:
        ask_or_abort(self.ctx, payload["text"])


KIND = Prompt()
