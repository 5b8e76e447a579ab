"""Sequential estimators: filters that take the samples one by one, in order (Crassidis, Lai and
Harman's sequential centered, EKF and UKF, and the energy-state forms of ADR 0009).

:mod:`~rig.calibration.sequential.realtime` builds a filter from :class:`FilterOptions` and runs
it (also live, sample by sample, in the ``live_calibrate`` step); :mod:`.zmodel` is their
measurement model, :mod:`.filters` the paper's EKF and UKF, :mod:`.energy_filter` the
energy-state filters, :mod:`.filters_filterpy` the filterpy backend.
:mod:`rig.calibration.estimators` lists which of them ``calibrate`` offers.
"""
