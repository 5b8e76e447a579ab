"""Sequential estimators: filters that take the samples one by one, in order (Crassidis, Lai and
Harman's sequential centered, EKF and UKF, and the energy-state forms of ADR 0009).

Every sequential estimator, by name: the one place a new one is registered. To add one, write a
module here with ``KIND = SequentialKind(...)`` (:mod:`.kind`: its name, description and how it
builds its filter from :class:`~.kind.FilterOptions`) and add the module to the tuple below
(docs/architecture.md). The estimator table (:mod:`rig.calibration.estimators`) lists them after
the batch estimators. Importing this package costs no numpy.

:mod:`.realtime` builds a filter and runs it (also live, sample by sample, in the
``live_calibrate`` step); :mod:`.zmodel` is their measurement model, :mod:`.filters` the paper's
EKF and UKF, :mod:`.energy_filter` the energy-state filters, :mod:`.filters_filterpy` the filterpy
backend, :mod:`.guard` the divergence watch.
"""

from __future__ import annotations

from rig.calibration.sequential import centered_seq, ekf, rls, ukf
from rig.calibration.sequential.kind import SequentialKind
from rig.errors import CalibrationError

KINDS: dict[str, SequentialKind] = {m.KIND.name: m.KIND for m in (centered_seq, ekf, ukf, rls)}
"""Every sequential estimator, in the order the CLI lists them."""


def sequential_kind(name: str) -> SequentialKind:
    """The estimator called ``name``; an unknown name is a one-line error listing the known ones."""
    try:
        return KINDS[name]
    except KeyError:
        raise CalibrationError(
            f"unknown sequential method {name!r}: use one of {', '.join(KINDS)}"
        ) from None
