"""The field a cage leaves at a commanded zero, which the DUT sees on top of every set-point.

A set-point becomes currents through the cage model in use, ``I = K^-1 (B - B0)``: with a model
from a characterization (the rig's calibration record, or a ``characterize_cage`` step earlier in
the same run) ``B0`` is the lab's field and the DUT sees the set-point; with the rig's nominal
model (``B0 = 0``) it sees the set-point plus the lab's field (tens of uT: it moves every field's
magnitude and direction, and so what a scalar fit or a live filter learns). That field is what an
untrimmed ``null_field`` step of an earlier run measured with the same model
(``null_residual_ut``); without one it is unknown and the prediction says so.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from itertools import chain
from pathlib import Path
from typing import Any

import numpy as np

from rig.config import RigConfig
from rig.output_limits import cage_model
from rig.prediction.noise import results_of
from rig.steps import cage_model_measured_before
from rig.steps.null_field import NoiseFloorResult
from rig.steps.vocabulary import Procedure, Step


@dataclass(frozen=True)
class Background:
    """The field at the cage's commanded zero (uT, cage frame) and where it comes from;
    ``known`` is False when a nominal model's lab field has not been measured (predicted as 0)."""

    field_ut: tuple[float, float, float]
    source: str
    known: bool = True

    def for_step(self, proc: Procedure, step: Step) -> np.ndarray:
        """What ``step`` sees: zero after a ``characterize_cage`` step of the same procedure
        (the run then uses the model it measured), else :attr:`field_ut` (uT)."""
        if cage_model_measured_before(proc, step):
            return np.zeros(3)
        return np.asarray(self.field_ut, float)


def background_field(cfg: RigConfig | None, runs_dir: Path | None, dut: str,
                     this_run: Mapping[str, Any] | None = None) -> Background:  # fmt: skip
    """The field the rig's cage model leaves at zero: none with a characterized model, else the
    newest untrimmed null among ``this_run``'s results (a run in progress), else among device
    ``dut``'s runs in ``runs_dir`` (see the module)."""
    model = cage_model(cfg) if cfg is not None else None
    if model is None or not model.meta.get("nominal"):
        return Background((0.0, 0.0, 0.0), "the cage's calibration record (its B0 is the lab's"
                          " field)" if model is not None else "no cage model")  # fmt: skip
    earlier = results_of(runs_dir, dut) if runs_dir is not None else iter(())
    for run_id, results in chain([("in progress", this_run or {})], earlier):
        for name, value in reversed(list(results.items())):
            found = NoiseFloorResult.from_dict(value) if isinstance(value, Mapping) else None
            if found is not None and found.null_residual_ut is not None:
                return Background(found.null_residual_ut, f"the field at the untrimmed null"
                                  f" '{name}' of run {run_id} (nominal cage model)")  # fmt: skip
    return Background((0.0, 0.0, 0.0), "unknown: the cage model is nominal (B0 = 0) and no run"
                      " measured the field it leaves at zero; predicted as if nulled (run a"
                      " null_field step, or characterize the cage)", known=False)  # fmt: skip
