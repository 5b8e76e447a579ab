"""Calibration core: the measurement model, its estimators and their uncertainty.

Pure numpy/scipy, no I/O. Start with :func:`calibrate` on :class:`Samples`.
"""

from rig.calibration.fit import METHODS, Method, calibrate, default_method
from rig.calibration.params import Calibration, Crassidis, Springmann
from rig.calibration.residuals import Samples
from rig.calibration.result import CalibrationResult

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
