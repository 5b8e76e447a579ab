"""``live_calibrate``: sweep random fields while a sequential filter calibrates the DUT from every
settled sample; stop as soon as each target 1-sigma is met (see rig.steps.live_calibrate_run)."""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

import timebase
from rig.calibration.estimators import method_names
from rig.calibration.record import CALIBRATION_VALUES
from rig.errors import RigError
from rig.steps.base import Array, FieldStepKind, RunContext, StepExecution
from rig.steps.geometry import sphere_fields
from rig.steps.live_calibrate_run import LiveCalibration
from rig.steps.null_field import latest_noise_floor
from rig.steps.vocabulary import (
    MAX_FIELD_SETPOINTS_PER_STEP,
    LoadCommand,
    ProcedureError,
    RigTiming,
    Step,
    StepParam,
    suggest,
)

FORECAST_WAIT_S = 10.0
"""Longest wait at the step's end for its forecast, still being computed (s)."""


class LiveCalibrate(FieldStepKind):
    name = "live_calibrate"
    summary = "sweep while a sequential filter calibrates; stop when the target sigmas are met"
    result_values = (*CALIBRATION_VALUES, "live.*", "filter.*")
    params: ClassVar[dict[str, StepParam]] = {
        "method": StepParam("str", "ukf", choices=method_names(kind="sequential")),
        "telemetry": StepParam("list_str", []),
        "targets": StepParam("dict", {}),
        "stop_on_target": StepParam("str", "yes", choices=("yes", "no")),
        "min_s": StepParam("float", 5.0, 0.0, 86400.0),
        "max_s": StepParam("float", 60.0, 1.0, 86400.0),
        "magnitude_ut": StepParam("range2", [20.0, 50.0], 0.0, 1000.0),
        "dwell_s": StepParam("float", 0.8, 0.05, 3600.0),
        "seed": StepParam("int", 1, 0, 2**31),
        "noise_nt": StepParam("float", 0.0, 0.0, 1e6),
        "settle_s": StepParam("float", 0.25, 0.0, 60.0),
        "magnetometer": StepParam("str", "dut"),
    }

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        """Telemetry among the loads, targets known and positive, a consistent stop rule."""
        from rig.calibration.targets import SIGMA_TARGETS

        for ch in params["telemetry"]:
            if ch not in loads:
                raise ProcedureError(
                    f"{where}: telemetry '{ch}' is not in the procedure's 'loads' list{suggest(ch, list(loads))}"
                )
        targets = params["targets"]
        for key, value in targets.items():
            if key not in SIGMA_TARGETS:
                raise ProcedureError(
                    f"{where}: unknown target '{key}'{suggest(key, SIGMA_TARGETS)}; targets are: {', '.join(SIGMA_TARGETS)}"
                )
            if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
                raise ProcedureError(
                    f"{where}: target '{key}' must be a positive 1-sigma, got {value!r}"
                )
            targets[key] = float(value)
        if "k_ut_per_a" in targets and not params["telemetry"]:
            raise ProcedureError(f"{where}: target 'k_ut_per_a' needs 'telemetry' channels")
        if params["stop_on_target"] == "yes" and not targets:
            raise ProcedureError(
                f"{where}: stop_on_target needs 'targets', e.g. {{bias_nt: 30, scale: 0.002}}; or set stop_on_target: no"
            )
        setpoints = params["max_s"] / params["dwell_s"]
        if setpoints > MAX_FIELD_SETPOINTS_PER_STEP:
            raise ProcedureError(
                f"{where}: max_s / dwell_s makes {setpoints:.0f} field set-points, more than"
                f" {MAX_FIELD_SETPOINTS_PER_STEP} (MAX_FIELD_SETPOINTS_PER_STEP): lengthen dwell_s"
                " or shorten max_s"
            )
        if params["min_s"] > params["max_s"]:
            raise ProcedureError(f"{where}: min_s must not exceed max_s")

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        p = step.params
        n = math.ceil(p["max_s"] / p["dwell_s"])
        return [
            (i * p["dwell_s"], f)
            for i, f in enumerate(sphere_fields(n, p["magnitude_ut"], p["seed"]))
        ]

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return LiveStep(ctx, step)


class LiveStep(StepExecution):
    """Connects the filter to the samplers and the field/load changes for the step's time."""

    def __init__(self, ctx: RunContext, step: Step) -> None:
        super().__init__(ctx, step)
        params = step.params
        mags = ctx.proc.magnetometers
        dut = mags.get(params["magnetometer"], params["magnetometer"])
        ref = mags.get("reference")
        if ref is None or dut not in ctx.samplers:
            raise RigError(
                f"{ctx.proc.path}: live_calibrate needs the '{params['magnetometer']}' and"
                " 'reference' magnetometers under 'magnetometers'"
            )
        noise_nt = params["noise_nt"] or self._noise_nt(params["magnetometer"])
        self.channels = list(params["telemetry"])
        self.live = LiveCalibration(params, noise_nt / 1000.0, timebase.monotonic(), self._loads_now,
                                    ctx.correction)  # fmt: skip
        self.ref, self.dut = ref, dut
        ctx.samplers[ref].listeners.append(self.live.on_reference)
        ctx.samplers[dut].listeners.append(self.live.on_dut)
        ctx.change_listeners.append(self.live)
        ctx.status_sources.append(self.live.status)
        ctx.live_sources.append(self.live.page_state)
        self.live.start()
        self._forecaster = timebase.Thread(self._forecast, args=(noise_nt,),
                                           name="live-forecast", daemon=True)  # fmt: skip
        self._forecaster.start()
        self.stop = self.live.done
        ctx.event("info", f"live calibration: {params['method']} at {noise_nt:.3g} nT noise,"
                          f" targets {params['targets'] or 'none'}")  # fmt: skip

    def _forecast(self, noise_nt: float) -> None:
        """The step's plan forecast (about a second of computing: beside the sweep, not before
        it); a plan that cannot be forecast only loses the ETA."""
        try:
            self.live.set_forecast(self.ctx.live_forecast(self.step, noise_nt))
        except Exception as exc:  # advisory: whatever went wrong, the step runs on without it
            self.live.set_forecast(None, f"no forecast: {type(exc).__name__}: {exc}")

    def _noise_nt(self, role: str) -> float:
        """The noise of ``role``'s pairs with the reference from the newest null field (nT): the
        filter pairs each DUT sample with one reference sample, so both noises count but field
        noise both see at once does not (the root sum square of the two floors counted it twice:
        28 against 23 nT on the simulator, mean NIS 0.48). Older results: the root sum square."""
        floor = latest_noise_floor(self.ctx.results)
        noise = floor.pair_noise_nt(role) if floor is not None else None
        if noise is not None:
            return noise
        raise RigError(
            f"{self.ctx.proc.path}: live_calibrate needs the noise: put a null_field step before it,"
            " or give noise_nt"
        )

    def _loads_now(self, t: float) -> np.ndarray:
        """Load currents (A) for the filter: the read-back once it is newer than the last change's
        settling, the commanded value before that."""
        out = []
        for ch in self.channels:
            meas = self.ctx.measured_loads.get(ch)
            fresh = meas is not None and meas[0] >= self.live.quiet_after
            out.append(meas[1] if fresh and meas is not None else self.ctx.commanded_loads[ch])
        return np.array(out, float)

    def _detach(self) -> None:
        for fn, dev in ((self.live.on_reference, self.ref), (self.live.on_dut, self.dut)):
            listeners = self.ctx.samplers[dev].listeners
            if fn in listeners:
                listeners.remove(fn)
        if self.live in self.ctx.change_listeners:
            self.ctx.change_listeners.remove(self.live)
        if self.live.status in self.ctx.status_sources:
            self.ctx.status_sources.remove(self.live.status)
        if self.live.page_state in self.ctx.live_sources:
            self.ctx.live_sources.remove(self.live.page_state)

    def wind_down(self) -> None:
        """Disconnect the filter; after an early stop, switch the step's loads back to zero."""
        self._detach()
        if self.live.done.is_set():
            for ch in self.step.loads:
                off = LoadCommand(0.0, {"channel": ch, "current_a": 0.0})
                self.ctx.command(self.step.index, off, timebase.monotonic())

    def finish(self, t_start: float, t_end: float) -> None:
        self._forecaster.join(timeout=FORECAST_WAIT_S)  # a short step: the result has it too
        result = self.live.finish(self.ctx.folder, self.step.name, timebase.monotonic())
        self.ctx.record_result(self.step.name, result)
        self.ctx.event(
            "info", f"live calibration '{self.step.name}' stopped: {result['live']['stopped']}"
        )

    def abort(self) -> None:
        """The run is ending: let go of the samplers and the worker."""
        self._detach()
        self.live.stop()


KIND = LiveCalibrate()
