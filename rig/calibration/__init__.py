"""Calibration core: the measurement model, its estimators and their uncertainty.

Pure numpy/scipy, no I/O. Start with :func:`calibrate` on :class:`Samples`; the estimators it can
run are the rows of :mod:`rig.calibration.estimators` (batch and sequential).

The names below are loaded on first use, so that ``rig.calibration.estimators`` (which the CLI
reads to build its parser) can be imported without numpy.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rig.calibration.estimators import Method
    from rig.calibration.fit import METHODS, calibrate, default_method
    from rig.calibration.params import Calibration, Crassidis, Springmann
    from rig.calibration.residuals import Samples
    from rig.calibration.result import CalibrationResult

_HOME = {
    "METHODS": "fit",
    "Method": "estimators",
    "calibrate": "fit",
    "default_method": "fit",
    "Calibration": "params",
    "Crassidis": "params",
    "Springmann": "params",
    "Samples": "residuals",
    "CalibrationResult": "result",
}

__all__ = [
    "METHODS",
    "Calibration",
    "CalibrationResult",
    "Crassidis",
    "Method",
    "Samples",
    "Springmann",
    "calibrate",
    "default_method",
]


def __getattr__(name: str) -> object:
    home = _HOME.get(name)
    if home is None:
        raise AttributeError(f"module 'rig.calibration' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"rig.calibration.{home}"), name)
    globals()[name] = value
    return value
