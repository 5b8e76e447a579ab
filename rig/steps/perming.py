"""``perming``: the DUT's offset at null field before and after a strong field (the shock), and
after a set/reset pulse where the DUT has one (:mod:`rig.characterization.perming`).

Timeline: a null-field hold, the shock field (``shock_ut`` along ``direction``, within the cage's
limits like every field) for ``shock_s``, a null-field hold, then (``reset: auto`` and a DUT
whose driver can pulse its set/reset strap, such as the HMR2300) one pulse and a last hold. Such
a DUT pulses automatically before every reading by default, which hides perming, so the step
turns that off for its duration and back on at its end, whatever the end. Each hold's offset is
the DUT (corrected by the run's latest calibration) less the cage's reference; the result is the
shift after the shock with its sigma and significance, and what the reset left of it.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

import timebase
from drivers.protocols import SetReset
from rig.analysis import settled_samples, to_cage_frame
from rig.characterization.perming import HoldMean, OffsetShift, hold_mean, offset_shifts
from rig.errors import RigError
from rig.steps.at_rest import offsets_at_rest
from rig.steps.base import Array, FieldStepKind, RunContext, StepExecution
from rig.steps.vocabulary import (
    ActionCommand,
    Command,
    FieldPayload,
    ProcedureError,
    RigTiming,
    Step,
    StepParam,
)


@dataclass(frozen=True)
class PermingResult:
    """The holds' offsets (nT), the shift the shock left and what the reset left of it."""

    shock_ut: float
    direction: tuple[float, ...]
    shock_field_ut: tuple[float, ...]
    holds: tuple[HoldMean, ...]
    shift: OffsetShift
    after_reset: OffsetShift | None
    reset_note: str
    calibrated: bool

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping (criteria: ``shift_abs_nt``, ``significance_sigma``,
        ``reset_residual_abs_nt``)."""
        s, r = self.shift, self.after_reset
        return {
            "shock_ut": self.shock_ut, "direction": list(self.direction),
            "shock_field_ut": list(self.shock_field_ut),
            "shock_abs_ut": float(np.linalg.norm(self.shock_field_ut)),
            "offsets_nt": [list(h.mean_nt) for h in self.holds],
            "offset_sigmas_nt": [list(h.sigma_nt) for h in self.holds],
            "samples": [h.samples for h in self.holds],
            "shift_nt": list(s.shift_nt), "shift_sigma_nt": list(s.sigma_nt),
            "shift_abs_nt": s.size_nt, "significance_sigma": s.significance_sigma,
            "detected": s.detected,
            "reset_residual_nt": list(r.shift_nt) if r else None,
            "reset_residual_sigma_nt": list(r.sigma_nt) if r else None,
            "reset_residual_abs_nt": r.size_nt if r else None,
            "reset_note": self.reset_note, "calibrated": self.calibrated,
        }  # fmt: skip


class Perming(FieldStepKind):
    name = "perming"
    summary = "the DUT's offset before and after a strong field, and after a set/reset pulse"
    result_values = ("shock_field_ut", "shock_abs_ut", "shift_nt", "shift_sigma_nt", "shift_abs_nt", "significance_sigma", "detected",
                     "reset_residual_nt", "reset_residual_abs_nt", "offsets_nt", "samples",
                     "calibrated")  # fmt: skip
    params: ClassVar[dict[str, StepParam]] = {
        "shock_ut": StepParam("float", 90.0, 1.0, 10000.0),
        "direction": StepParam("vec3", [1.0, 0.0, 0.0]),
        "shock_s": StepParam("float", 5.0, 0.1, 3600.0),
        "hold_s": StepParam("float", 60.0, 2.0, 86400.0),
        "settle_s": StepParam("float", 2.0, 0.0, 600.0),
        "reset": StepParam("str", "auto", choices=("auto", "no")),
        "trim": StepParam("str", "yes", choices=("yes", "no")),
        "magnetometer": StepParam("str", "dut"),
    }

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        if float(np.linalg.norm(params["direction"])) == 0.0:
            raise ProcedureError(f"{where}: direction must not be [0, 0, 0]")
        if params["settle_s"] >= params["hold_s"]:
            raise ProcedureError(f"{where}: settle_s must be shorter than hold_s")

    def field_payload(self, step: Step, field_ut: Array) -> FieldPayload:
        # the nulls closed on the reference (the DUT's uncalibrated scale would otherwise turn
        # the lab field's drift between the holds into a shift); the shock as planned
        trim = step.params["trim"] == "yes" and not np.any(field_ut)
        return {"field_ut": [float(v) for v in field_ut], "trim": trim}

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        p = step.params
        d = np.asarray(p["direction"], float)
        shock = float(p["shock_ut"]) * d / float(np.linalg.norm(d))
        hold, dwell = float(p["hold_s"]), float(p["shock_s"])
        return [(0.0, np.zeros(3)), (hold, shock), (hold + dwell, np.zeros(3))]

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        p = step.params
        holds = 3 if p["reset"] == "auto" else 2
        return holds * float(p["hold_s"]) + float(p["shock_s"])

    def compile(self, step: Step, base: Path, timing: RigTiming) -> tuple[list[Command], float]:
        cmds, duration = super().compile(step, base, timing)
        if step.params["reset"] == "auto":
            p = step.params
            t = 2 * float(p["hold_s"]) + float(p["shock_s"])
            cmds.append(ActionCommand(t, self.name, {"action": "pulse"}))
        return cmds, duration

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return MeasurePerming(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        if not isinstance(result, Mapping) or "shift_nt" not in result:
            return []
        shift = ", ".join(f"{v:+.2f} +- {s:.2f}" for v, s in
                          zip(result["shift_nt"], result["shift_sigma_nt"], strict=True))  # fmt: skip
        seen = "detected" if result["detected"] else "not detected"
        line = (f"Perming '{name}' ({result['shock_abs_ut']:.1f} uT at the DUT): offset shift {shift} nT"
                f" (x, y, z), {result['shift_abs_nt']:.2f} nT, {result['significance_sigma']:.1f}"
                f" sigma: {seen}")  # fmt: skip
        if not result["calibrated"]:
            line += ("; the DUT uncalibrated: its scale errors let the lab field's drift through"
                     " as a few percent of it")  # fmt: skip
        if result.get("reset_residual_abs_nt") is not None:
            line += f"; after the reset {result['reset_residual_abs_nt']:.2f} nT from before"
        return [line + f" ({result['reset_note']})"]

    def figures(self, reader: Any, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        if not isinstance(result, Mapping) or "offsets_nt" not in result:
            return []
        fig, ax = plt.subplots(figsize=(6.5, 3.4))
        means, sig = np.asarray(result["offsets_nt"]), np.asarray(result["offset_sigmas_nt"])
        labels = ["before", "after the shock", "after the reset"][: len(means)]
        x = np.arange(len(means))
        for i, axis in enumerate("xyz"):
            rel = means[:, i] - means[0, i]
            ax.errorbar(x + 0.08 * (i - 1), rel, yerr=sig[:, i], fmt="o-", capsize=3, label=axis)
        ax.set_xticks(x, labels)
        ax.set_ylabel("offset less before (nT)")
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        return [(f"Perming ('{name}'): offset at null field, 1-sigma", fig)]


class MeasurePerming(StepExecution):
    """Turns the DUT's automatic set/reset off for the step (and on again at its end), pulses it
    when the timeline says, and after the holds measures the shift."""

    def __init__(self, ctx: RunContext, step: Step) -> None:
        super().__init__(ctx, step)
        mags = ctx.proc.magnetometers
        self.dut = mags.get(step.params["magnetometer"], step.params["magnetometer"])
        self.ref = mags.get("reference")
        if self.dut not in ctx.samplers or self.ref not in ctx.samplers:
            raise RigError(f"perming '{step.name}' needs the '{step.params['magnetometer']}' and"
                           " 'reference' magnetometers sampled by this run")  # fmt: skip
        sampler = ctx.samplers[self.dut]
        driver = getattr(sampler, "driver", None)
        self.resettable = step.params["reset"] == "auto" and isinstance(driver, SetReset)
        self.pulse_t: tuple[float, float] | None = None  # (started, done) monotonic s
        self._auto_off = False
        if self.resettable:
            with self._set_reset() as driver:
                driver.set_reset_auto(False)
            self._auto_off = True
            ctx.event("info", f"perming: '{self.dut}' automatic set/reset off for the step")

    def run(self, payload: dict[str, Any]) -> None:
        if payload.get("action") != "pulse" or not self.resettable:
            return
        started = timebase.monotonic()
        with self._set_reset() as driver:
            driver.set_reset_pulse()
        self.pulse_t = (started, timebase.monotonic())

    @contextmanager
    def _set_reset(self) -> Iterator[SetReset]:
        """The DUT's driver, its sampling paused, as the set/reset device ``resettable`` found."""
        with self.ctx.samplers[self.dut].paused() as driver:
            assert isinstance(driver, SetReset)  # only called when resettable
            yield driver

    def _restore(self) -> None:
        """The DUT's automatic set/reset back on (its state before the step)."""
        if self._auto_off:
            with self._set_reset() as driver:
                driver.set_reset_auto(True)
            self._auto_off = False

    def wind_down(self) -> None:
        self._restore()

    def after_safe(self) -> None:
        # after the outputs are off: a silent DUT's timeouts must not delay the safe state
        try:
            self._restore()
        except Exception as exc:  # the run is already ending on another error: say, go on
            self.ctx.event("error", f"perming: could not turn '{self.dut}' set/reset on: {exc}")

    def finish(self, t_start: float, t_end: float) -> None:
        p = self.step.params
        windows, shock = self._windows(t_start, t_end)
        rests = offsets_at_rest(self.ctx, self.dut, self.ref, windows, float(p["settle_s"]))
        reader = self.ctx.open_reader()
        try:
            at_shock = settled_samples(reader, str(self.ref), shock, 0.0)
        finally:
            reader.close()
        if len(at_shock) == 0:
            raise RigError(f"perming '{self.step.name}': no reference sample during the shock:"
                           " lengthen shock_s")  # fmt: skip
        # the field the DUT saw during the shock: the reference's, through its certificate
        field = to_cage_frame(at_shock[:, 1:], self.ctx.correction).mean(axis=0)
        holds = []
        names = ("before the shock", "after the shock", "after the reset")
        for name, rest in zip(names, rests, strict=False):
            if len(rest.offsets_nt) < 10:
                raise RigError(f"perming '{self.step.name}': {len(rest.offsets_nt)} settled"
                               f" samples in the hold {name}: lengthen hold_s")  # fmt: skip
            holds.append(hold_mean(rest.offsets_nt))
        shifts = offset_shifts([r.t_s for r in rests[: len(holds)]],
                               [r.offsets_nt for r in rests[: len(holds)]])  # fmt: skip
        shift, after_reset = shifts[0], (shifts[1] if len(shifts) > 1 else None)
        result = PermingResult(float(p["shock_ut"]), tuple(float(v) for v in p["direction"]),
                               tuple(float(v) for v in field), tuple(holds), shift, after_reset,
                               self._reset_note(), rests[0].calibrated)  # fmt: skip
        self.ctx.record_result(self.step.name, result.to_dict())

    def _windows(self, t_start: float, t_end: float) -> tuple[list[tuple[float, float]],
                                                                tuple[float, float]]:  # fmt: skip
        """The holds' spans and the shock's once it is reached (monotonic s): from the step's
        field commands and the pulse."""
        reader = self.ctx.open_reader()
        try:
            fields = [(float(pl.get("t_issued", t)), t) for t, s, k, pl in reader.commands()
                      if s == self.step.index and k == "field"]  # fmt: skip
        finally:
            reader.close()
        if len(fields) < 3:
            raise RigError(f"perming '{self.step.name}': the step ended before its holds")
        spans = [(t_start, fields[1][0]), (fields[2][1], t_end)]
        if self.pulse_t is not None:
            settle = float(self.step.params["settle_s"])  # the pulse is no field change
            spans = [spans[0], (fields[2][1], self.pulse_t[0]), (self.pulse_t[1] + settle, t_end)]
        return spans, (fields[1][1], fields[2][0])

    def _reset_note(self) -> str:
        if self.pulse_t is not None:
            return "one set/reset pulse, automatic set/reset off during the step"
        if self.step.params["reset"] == "no":
            return "no reset (reset: no)"
        return f"no reset: '{self.dut}' has no set/reset the rig can drive"


KIND = Perming()
