"""``calibrate``: fit the DUT (batch estimator) from the named steps' settled samples."""

from __future__ import annotations

from typing import Any, ClassVar

from rig.analysis import calibrate_run
from rig.calibration.estimators import method_names
from rig.calibration.record import CALIBRATION_VALUES
from rig.steps.base import StepExecution, StepKind
from rig.steps.vocabulary import StepParam


class Calibrate(StepKind):
    name = "calibrate"
    summary = "fit the DUT from the recorded steps (batch)"
    result_values = CALIBRATION_VALUES
    params: ClassVar[dict[str, StepParam]] = {
        "model": StepParam("str", "vector", choices=("vector", "scalar")),
        "method": StepParam("str", "", choices=("", *method_names(kind="batch"))),
        "magnetometer": StepParam("str", "dut"),
        "telemetry": StepParam("list_str", []),
        "steps": StepParam("list_str", []),
        "noise_nt": StepParam("float", 0.0, 0.0, 1e6),
        "settle_s": StepParam("float", 0.25, 0.0, 60.0),
        # a thermometer the run recorded (rig configuration): fits the temperature coefficients
        "temperature": StepParam("str", ""),
        "temperature_ref_c": StepParam("float", 25.0, -100.0, 300.0),
    }

    def thermometers(self, step: Any) -> tuple[str, ...]:
        return (step.params["temperature"],) if step.params.get("temperature") else ()

    def execution(self, ctx: Any, step: Any) -> StepExecution:
        return Fit(ctx, step)


class Fit(StepExecution):
    def run(self, payload: dict[str, Any]) -> None:
        from rig.cage_budget import cage_terms
        from rig.steps import field_kinds

        ctx = self.ctx
        model = getattr(ctx.controller, "model", None)
        cage_cfg = ctx.cfg.cage if ctx.cfg is not None else None
        cage = cage_terms(ctx.correction, model.to_dict() if model is not None else None,
                          cage_cfg.ambient_gradient_nt_per_m if cage_cfg is not None else 0.0)  # fmt: skip
        reader = ctx.open_reader()
        try:
            result = calibrate_run(reader, payload, ctx.proc.magnetometers, ctx.correction,
                                   field_kinds(), cage)  # fmt: skip
        finally:
            reader.close()
        self.ctx.record_result(self.step.name, result)


KIND = Calibrate()
