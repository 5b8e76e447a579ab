"""Moved to :mod:`rig.calibration.sequential.realtime`. Kept only for the names
``rig/steps/live_calibration.py`` imports from here; delete once it imports the new module."""

from rig.calibration.sequential.realtime import FilterOptions, filter_estimate, make_filter

__all__ = ["FilterOptions", "filter_estimate", "make_filter"]
