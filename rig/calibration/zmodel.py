"""Moved to :mod:`rig.calibration.sequential.zmodel`. Kept only for the name
``rig/steps/live_calibration.py`` imports from here; delete once it imports the new module."""

from rig.calibration.sequential.zmodel import z_sample

__all__ = ["z_sample"]
