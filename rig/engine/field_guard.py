"""The cage's field limit held against the field measured, not only the field modelled: every
reading of the cage's reference magnetometer during a run is compared with ``[cage]
max_field_ut``, and one beyond it is a fault (``RigSession.fail``): the run ends through the safe
path. The coil currents are bounded by the cage model; this catches what the model does not know
(an uncharacterized cage's ambient field, a wrong nameplate, a reference certificate whose offset
is wrong, a coil driven by something else).

Both the raw reading and the reading through the reference's certificate are judged, so a wrong
certificate cannot hide a real field. A margin (:data:`MARGIN_FRACTION` of the limit plus
:data:`MARGIN_UT`) keeps a field asked at the limit, with the reference's own noise and scale error,
from ending a good run.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rig.analysis import to_cage_frame
from rig.cage_budget import certificate_of
from rig.config import RigConfig
from rig.engine.sampling import SensorSampler
from rig.engine.session import RigSession

MARGIN_FRACTION = 0.02
"""Part of the field limit a reading may exceed it by before it is a fault (the reference's scale
error and the trim's residual at a field asked at the limit)."""
MARGIN_UT = 0.5
"""And this much more (uT): the reference's noise and offset."""


class FieldGuard:
    """A sampler listener: a reading beyond the field limit fails the session, once."""

    def __init__(self, rig: RigSession, reference: str, max_field_ut: float,
                 certificate: dict[str, Any] | None) -> None:  # fmt: skip
        self.rig = rig
        self.reference = reference
        self.max_field_ut = max_field_ut
        self.trip_ut = max_field_ut * (1.0 + MARGIN_FRACTION) + MARGIN_UT
        self.certificate = certificate
        self.tripped = False

    def __call__(self, t: float, xyz: tuple[float, float, float]) -> None:
        if self.tripped:
            return
        reading = np.asarray(xyz, float)
        seen = float(np.linalg.norm(reading))
        if self.certificate is not None:
            seen = max(seen, float(np.linalg.norm(to_cage_frame(reading, self.certificate))))
        if seen > self.trip_ut:  # NaN compares False: a frozen or broken sensor is health's
            self.tripped = True
            self.rig.fail(f"{self.reference} reads |B| = {seen:.1f} uT, beyond the cage's"
                          f" {self.max_field_ut:g} uT limit (max_field_ut); the outputs are off:"
                          " characterize the cage (rig run cage-characterization) and check the"
                          " reference's certificate before running again")  # fmt: skip


def guard_the_field(rig: RigSession, cfg: RigConfig,
                    samplers: dict[str, SensorSampler]) -> FieldGuard | None:  # fmt: skip
    """Hold the cage's field limit on every reading of its reference, when the run samples it
    (None: no cage, no reference, or the run does not read it)."""
    cage = cfg.cage
    if cage is None or cage.reference is None or cage.reference not in samplers:
        return None
    guard = FieldGuard(rig, cage.reference, cage.max_field_ut,
                       certificate_of(cfg, cage.reference))  # fmt: skip
    samplers[cage.reference].listeners.append(guard)
    return guard
