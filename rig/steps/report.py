"""``report``: ask for the acceptance report, written once the run is closed and sealed (so it
shows the final status and verdict and the digest of the data as they will stay)."""

from __future__ import annotations

from typing import Any, ClassVar

from rig.steps.base import StepExecution, StepKind
from rig.steps.vocabulary import StepParam


class Report(StepKind):
    name = "report"
    summary = "write the acceptance report when the run closes"
    params: ClassVar[dict[str, StepParam]] = {}

    def execution(self, ctx: Any, step: Any) -> StepExecution:
        return AskForReport(ctx, step)


class AskForReport(StepExecution):
    def run(self, payload: dict[str, Any]) -> None:
        self.ctx.request_report()
        self.ctx.event("info", "the report is written when the run closes")


KIND = Report()
