"""The spacecraft's attitude dynamics: Basilisk's rigid-body ``Spacecraft`` hub with an
``MtbEffector`` (three orthogonal torque rods along the body axes), stepped by the loop.

Basilisk is imported here only, when a loop starts: the rest of the rig never needs it
(``pip install -e '.[hil]'``). The field the rods push against is the true field along the orbit,
in the inertial frame, written into the effector's magnetic-field message every step; the rods'
dipoles are held over the step (zero-order hold), as a flight computer's commands are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from rig.errors import RigError

Array = npt.NDArray[np.float64]
INSTALL_HINT = "pip install -e '.[hil]' (Basilisk, the package 'bsk')"


class DynamicsUnavailableError(RigError):
    """Basilisk is not installed: one line naming the install."""


@dataclass(frozen=True)
class Spacecraft:
    """A rigid spacecraft with three torque rods along its body axes.

    ``inertia_kg_m2``: the 3 x 3 inertia about the centre of mass (body frame, kg m^2);
    ``max_dipole_am2``: each rod's largest dipole (A m^2); ``rate_deg_s``: the initial body
    rate (deg/s, body frame); ``mrp``: the initial attitude (modified Rodrigues parameters of
    body relative to inertial)."""

    inertia_kg_m2: tuple[tuple[float, float, float], ...]
    max_dipole_am2: float
    rate_deg_s: tuple[float, float, float]
    mrp: tuple[float, float, float] = (0.1, 0.2, -0.1)
    mass_kg: float = 4.0


def _basilisk() -> Any:
    try:
        from Basilisk.architecture import messaging
        from Basilisk.simulation import MtbEffector, spacecraft
        from Basilisk.utilities import RigidBodyKinematics, SimulationBaseClass, macros
    except ImportError:
        raise DynamicsUnavailableError(
            f"the closed loop needs Basilisk, which is not installed: {INSTALL_HINT}"
        ) from None
    return messaging, MtbEffector, spacecraft, RigidBodyKinematics, SimulationBaseClass, macros


class BasiliskDynamics:
    """Basilisk propagating ``craft`` in steps of ``step_s`` (s) of its own time, from 0."""

    def __init__(self, craft: Spacecraft, step_s: float) -> None:
        messaging, mtb_module, sc_module, rbk, base, macros = _basilisk()
        self._messaging, self._rbk, self._macros = messaging, rbk, macros
        self.step_s = step_s
        self.t_s = 0.0
        sim = base.SimBaseClass()
        sim.SetProgressBar(False)
        sim.CreateNewProcess("dynamics").addTask(
            sim.CreateNewTask("attitude", macros.sec2nano(step_s))
        )
        sc = sc_module.Spacecraft()
        sc.ModelTag = "spacecraft"
        sc.hub.mHub = craft.mass_kg
        sc.hub.IHubPntBc_B = [list(row) for row in craft.inertia_kg_m2]
        sc.hub.sigma_BNInit = [[v] for v in craft.mrp]
        sc.hub.omega_BN_BInit = [[float(v)] for v in np.radians(craft.rate_deg_s)]
        sim.AddModelToTask("attitude", sc)
        rods = mtb_module.MtbEffector()
        rods.ModelTag = "torque rods"
        sc.addDynamicEffector(rods)
        sim.AddModelToTask("attitude", rods)
        layout = messaging.MTBArrayConfigMsgPayload()
        layout.numMTB = 3
        layout.GtMatrix_B = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        layout.maxMtbDipoles = [craft.max_dipole_am2] * 3
        # the messages live as long as the simulation reads them
        self._layout = messaging.MTBArrayConfigMsg().write(layout)
        self._cmd = messaging.MTBCmdMsg()
        self._cmd.write(messaging.MTBCmdMsgPayload())
        self._field = messaging.MagneticFieldMsg()
        self._field.write(messaging.MagneticFieldMsgPayload())
        rods.mtbParamsInMsg.subscribeTo(self._layout)
        rods.mtbCmdInMsg.subscribeTo(self._cmd)
        rods.magInMsg.subscribeTo(self._field)
        self._sim, self._sc, self._rods = sim, sc, rods
        sim.InitializeSimulation()

    def state(self) -> tuple[Array, Array]:
        """(MRP of body relative to inertial, body rate in rad/s, body frame) now."""
        st = self._sc.scStateOutMsg.read()
        return np.array(st.sigma_BN, float), np.array(st.omega_BN_B, float)

    def body_from_inertial(self) -> Array:
        """The direction cosine matrix [BN] now (rows: body axes in the inertial frame)."""
        sigma, _ = self.state()
        return np.array(self._rbk.MRP2C(sigma), float)

    def step(self, dipole_am2: Array, field_inertial_ut: Array) -> None:
        """Hold ``dipole_am2`` (A m^2, body frame; the effector clips each to its rod's
        largest) in ``field_inertial_ut`` (uT) for one step."""
        now = self._macros.sec2nano(self.t_s)
        field = self._messaging.MagneticFieldMsgPayload()
        field.magField_N = [float(v) * 1e-6 for v in field_inertial_ut]
        self._field.write(field, now)
        cmd = self._messaging.MTBCmdMsgPayload()
        cmd.mtbDipoleCmds = [float(v) for v in dipole_am2]
        self._cmd.write(cmd, now)
        self.t_s += self.step_s
        self._sim.ConfigureStopTime(self._macros.sec2nano(self.t_s))
        self._sim.ExecuteSimulation()
