"""Helmholtz-cage magnetometer test rig: configuration, calibration, procedures, reports."""

__version__ = "0.1.0"
