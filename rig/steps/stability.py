"""``stability``: hold the null field and measure how the DUT's offset wanders: its Allan deviation
per axis with 68 % confidence intervals, and its drift over 12 h with a sigma
(:mod:`rig.characterization.stability`).

At a null field a magnetometer reads its offset plus whatever the lab's field does; a reference
seeing the same field takes the latter out: each DUT sample less the reference interpolated to
its time (``reference: reference``, the cage's, inside the coils; ``ambient``, the rig's outside
ones; ``none``: nothing subtracted, and the result says the lab's field is in it). With a
calibration of the DUT earlier in the run, the DUT's readings are corrected by it first (its
scale and axes; otherwise a field change leaks through as a few percent of itself).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from rig.characterization.offset_noise import OffsetNoise
from rig.characterization.stability import (
    MIN_SAMPLES,
    AllanDeviation,
    allan_deviation,
    offset_drift,
)
from rig.errors import RigError
from rig.steps.at_rest import offsets_at_rest
from rig.steps.base import NullHoldKind, RunContext, StepExecution
from rig.steps.vocabulary import Step, StepParam

REFERENCES = ("reference", "ambient", "none")


@dataclass(frozen=True)
class StabilityResult:
    """A stability hold's figures (nT): Allan deviation per averaging time and axis with its
    68 % interval, at 1 s and its smallest (the floor), and the drift over 12 h with 1-sigma."""

    allan: AllanDeviation
    drift_nt_per_12h: tuple[float, ...]
    drift_sigma_nt_per_12h: tuple[float, ...]
    reference: str
    reference_note: str
    calibrated: bool
    samples: int
    hold_s: float
    noise: tuple[OffsetNoise, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping (criteria name ``adev_1s_max_nt``, ``adev_floor_max_nt``,
        ``drift_abs_max_nt_per_12h``)."""
        a = self.allan
        floor = np.min(np.asarray(a.adev_nt), axis=0)
        return {
            "allan": {"tau_s": list(a.tau_s), "adev_nt": [list(r) for r in a.adev_nt],
                      "low_nt": [list(r) for r in a.low_nt], "high_nt": [list(r) for r in a.high_nt],
                      "rate_hz": a.rate_hz},
            "adev_1s_nt": list(a.at(1.0)), "adev_1s_max_nt": max(a.at(1.0)),
            "adev_floor_nt": [float(v) for v in floor], "adev_floor_max_nt": float(max(floor)),
            "drift_nt_per_12h": list(self.drift_nt_per_12h),
            "drift_sigma_nt_per_12h": list(self.drift_sigma_nt_per_12h),
            "drift_abs_max_nt_per_12h": max(abs(v) for v in self.drift_nt_per_12h),
            "reference": self.reference, "reference_note": self.reference_note,
            "calibrated": self.calibrated, "samples": self.samples, "hold_s": self.hold_s,
            "noise_model": [n.to_dict() for n in self.noise], "warnings": list(a.notes),
        }  # fmt: skip


def read_allan(result: Any) -> AllanDeviation | None:
    """A stored stability result's Allan deviation; None when it is not one."""
    try:
        a = result["allan"]
        return AllanDeviation(tuple(a["tau_s"]), tuple(tuple(r) for r in a["adev_nt"]),
                              tuple(tuple(r) for r in a["low_nt"]),
                              tuple(tuple(r) for r in a["high_nt"]), float(a["rate_hz"]))  # fmt: skip
    except (KeyError, TypeError, ValueError):
        return None


class Stability(NullHoldKind):
    name = "stability"
    summary = "hold the null field: the DUT offset's Allan deviation and drift per 12 h"
    result_values = ("adev_1s_nt", "adev_1s_max_nt", "adev_floor_nt", "adev_floor_max_nt",
                     "drift_nt_per_12h", "drift_sigma_nt_per_12h", "drift_abs_max_nt_per_12h",
                     "samples", "hold_s", "calibrated", "reference")  # fmt: skip
    params: ClassVar[dict[str, StepParam]] = {
        "hold_s": StepParam("float", 600.0, 20.0, 7 * 86400.0),
        "reference": StepParam("str", "reference", choices=REFERENCES),
        "trim": StepParam("str", "yes", choices=("yes", "no")),
        "settle_s": StepParam("float", 2.0, 0.0, 600.0),
        "magnetometer": StepParam("str", "dut"),
    }

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return MeasureStability(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        if not isinstance(result, Mapping) or read_allan(result) is None:
            return []
        drift = ", ".join(f"{v:+.2f} +- {s:.2f}" for v, s in
                          zip(result["drift_nt_per_12h"], result["drift_sigma_nt_per_12h"], strict=True))  # fmt: skip
        at1 = ", ".join(f"{v:.3g}" for v in result["adev_1s_nt"])
        floor = ", ".join(f"{v:.3g}" for v in result["adev_floor_nt"])
        lines = [f"Offset stability '{name}' ({result['hold_s']:g} s, {result['reference_note']}):"
                 f" Allan deviation at 1 s {at1} nT, floor {floor} nT (x, y, z); drift {drift}"
                 " nT per 12 h"]  # fmt: skip
        noise = result.get("noise_model") or []
        if noise:
            lines.append("  offset noise (x, y, z): white " + ", ".join(
                f"{n['white_nt_per_sqrt_hz']:.3g}" for n in noise) + " nT/sqrt(Hz), flicker "
                + ", ".join(f"{n['flicker_adev_nt']:.3g}" for n in noise) + " nT, random walk "
                + ", ".join(f"{n['walk_nt_per_sqrt_h']:.3g}" for n in noise) + " nT/sqrt(h)")  # fmt: skip
        return lines + [f"  {w}" for w in result.get("warnings") or []]

    def figures(self, reader: Any, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        allan = read_allan(result)
        if allan is None:
            return []
        fig, ax = plt.subplots(figsize=(7.0, 3.8))
        tau = np.asarray(allan.tau_s)
        dev, lo, hi = (np.asarray(v) for v in (allan.adev_nt, allan.low_nt, allan.high_nt))
        for i, axis in enumerate("xyz"):
            ax.errorbar(tau, dev[:, i], yerr=[dev[:, i] - lo[:, i], hi[:, i] - dev[:, i]],
                        fmt="o-", ms=3, lw=0.9, capsize=2, label=axis)  # fmt: skip
        white = float(np.mean(dev[0])) * np.sqrt(tau[0] / tau)
        ax.loglog(tau, white, "k:", lw=0.8, label="white noise (tau^-1/2)")
        floor = float(np.min(dev))
        ax.axhline(floor, color="0.5", ls="--", lw=0.8, label=f"floor {floor:.3g} nT")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("averaging time tau (s)")
        ax.set_ylabel("Allan deviation (nT)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        return [(f"Offset stability ('{name}'): Allan deviation, 68 % intervals", fig)]


class MeasureStability(StepExecution):
    """After the hold: the DUT less the reference, its Allan deviation and drift."""

    def finish(self, t_start: float, t_end: float) -> None:
        p = self.step.params
        mags = self.ctx.proc.magnetometers
        dut = mags.get(p["magnetometer"], p["magnetometer"])
        which = str(p["reference"])
        ref_dev, note = self._reference(which)
        # the reference through its certificate; an outside (ambient) one as it reads
        (rest,) = offsets_at_rest(self.ctx, dut, ref_dev, [(t_start, t_end)],
                                  float(p["settle_s"]), certified=which == "reference")  # fmt: skip
        t, offsets = rest.t_s, rest.offsets_nt
        if len(t) < MIN_SAMPLES:
            raise RigError(f"stability '{self.step.name}': {len(t)} settled samples of"
                           f" '{dut}': lengthen hold_s or check the magnetometer")  # fmt: skip
        allan = allan_deviation(t, offsets)
        drift = offset_drift(t, offsets)
        result = StabilityResult(allan, drift.per_12h_nt, drift.sigma_nt, str(p["reference"]),
                                 note, rest.calibrated, len(t), float(p["hold_s"]),
                                 drift.noise)  # fmt: skip
        for warning in allan.notes:
            self.ctx.event("warning", f"stability '{self.step.name}': {warning}")
        self.ctx.record_result(self.step.name, result.to_dict())

    def _reference(self, which: str) -> tuple[str | None, str]:
        """The device subtracted and what the result says of it."""
        if which == "none":
            return None, "nothing subtracted: the lab field's changes are in it"
        if which == "ambient":
            dev = self.ctx.cfg.cage.ambient if self.ctx.cfg.cage is not None else None
        else:
            dev = self.ctx.proc.magnetometers.get("reference")
        if dev is None or dev not in self.ctx.samplers:
            raise RigError(f"stability '{self.step.name}': reference: {which} names no sampled"
                           " magnetometer of this rig; use reference: none (the lab field's"
                           " changes then stay in the result)")  # fmt: skip
        return dev, f"the {which} magnetometer '{dev}' subtracted"


KIND = Stability()
