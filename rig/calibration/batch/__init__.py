"""Batch estimators: every sample at once.

:mod:`~rig.calibration.batch.linear` holds the linear initializers (centered least squares with
telemetry regressors, the algebraic ellipsoid, the cage vector least squares);
:mod:`~rig.calibration.batch.nonlinear` the iterative ones (scalar maximum likelihood, TWOSTEP,
robust reweighting). :mod:`rig.calibration.estimators` lists which of them ``calibrate`` offers.
"""
