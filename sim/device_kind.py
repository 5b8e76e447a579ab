"""The contract of a simulated device kind: how :class:`sim.cage.SimulatedCage` starts one.

A simulated device kind is one module (or one row in one) with a :class:`SimKind` and one line in
:data:`sim.device_kinds.KINDS`. Its ``start`` is given the cage (as :class:`CageHost`) and the
device's configuration (a supply's or a magnetometer's), builds the device on its real transport
and returns its entry in the endpoints document (what the rig's ``rig.toml`` needs to reach it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol

if TYPE_CHECKING:
    import numpy as np
    from pymodbus.simulator import SimDevice

    from sim.config import EndpointConfig, SimConfig
    from sim.i2c_bus import BusDevice, SimI2CBus
    from sim.physics import CagePhysics, Faults


class SerialDevice(Protocol):
    """A device on a serial line (a pty, or ``simpipe://<name>`` in simulated time): the path
    the rig opens, closed when the cage stops."""

    @property
    def path(self) -> str: ...

    def close(self) -> None: ...


class CageHost(Protocol):
    """What a device kind's ``start`` may use of the cage."""

    cfg: SimConfig
    physics: CagePhysics
    i2c_bus: SimI2CBus

    def serve_modbus(self, name: str, device: SimDevice, endpoint: EndpointConfig,
                     faults: Faults) -> dict[str, Any]: ...  # fmt: skip

    def add_serial(self, name: str, device: SerialDevice) -> None: ...

    def add_i2c(self, name: str, device: BusDevice) -> None: ...

    def field_reader(self, name: str) -> Callable[[float], np.ndarray]: ...


Section = Literal["supplies", "magnetometers"]


@dataclass(frozen=True)
class SimKind:
    """One simulated device kind: ``name`` as the simulator's TOML spells it (``kind = ...``) in
    ``section``; ``start(host, device_config, index)`` starts it (``index``: its position in the
    section, for per-device seeds) and returns its endpoint entry (``kind``, ``protocol``, ...)."""

    name: str
    section: Section
    start: Callable[[CageHost, Any, int], dict[str, Any]]
