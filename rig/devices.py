"""Open drivers from the rig configuration, and build the cage controller from them."""

from __future__ import annotations

from contextlib import ExitStack
from typing import Any

import numpy as np

from drivers.mag.ascii_line import AsciiLineMagnetometer, LineFormat
from drivers.mag.hmr2300 import Hmr2300
from drivers.mag.lis3mdl import Lis3mdl
from drivers.mag.rm3100 import Rm3100
from drivers.psu.regmap_device import MappedSupply, PolarityRelay
from drivers.psu.riden import RidenSupply
from drivers.regmap import RegisterMapError, load_map
from drivers.transport.modbus import ModbusLink
from rig.cage.controller import AxisDrive, CageController
from rig.cage.limits import CageLimits
from rig.cage.model import CageModel
from rig.config import DeviceConfig, RigConfig
from rig.errors import UserInputError


def _link(dev: DeviceConfig) -> ModbusLink:
    if dev.protocol == "modbus-tcp":
        return ModbusLink(name=dev.name, host=str(dev.get("host")), port=int(dev.get("port")),
                          device_id=int(dev.get("device_id", 1)), timeout_s=float(dev.get("timeout_s", 0.5)))  # fmt: skip
    return ModbusLink(name=dev.name, path=str(dev.get("path")), baudrate=int(dev.get("baudrate", 115200)),
                      parity=str(dev.get("parity", "N")), device_id=int(dev.get("device_id", 1)),
                      timeout_s=float(dev.get("timeout_s", 0.5)))  # fmt: skip


def open_device(dev: DeviceConfig, i2c_bus: Any | None = None) -> Any:
    """A driver for ``dev``. ``i2c_bus`` stands in for ``bus = "sim"`` (the simulator's bus)."""
    try:
        if dev.kind == "riden-rd60xx":
            return RidenSupply(_link(dev), name=dev.name, max_current_a=dev.get("max_current_a"))
        if dev.kind in ("regmap-supply", "regmap-eload"):
            return MappedSupply(_link(dev), load_map(str(dev.get("regmap"))), name=dev.name,
                                max_current_a=dev.get("max_current_a"))  # fmt: skip
        if dev.kind == "regmap-relay":
            return PolarityRelay(_link(dev), load_map(str(dev.get("regmap"))), name=dev.name)
        if dev.kind == "hmr2300":
            return Hmr2300(str(dev.get("path")), baudrate=int(dev.get("baudrate", 9600)),
                           device_id=dev.get("device_id"), name=dev.name)  # fmt: skip
        if dev.kind == "ascii-mag":
            fmt = LineFormat(delimiter=dev.get("delimiter"), columns=tuple(dev.get("columns", (0, 1, 2))),
                             scale_to_ut=float(dev.get("scale_to_ut", 1.0)))  # fmt: skip
            return AsciiLineMagnetometer(str(dev.get("path")), baudrate=int(dev.get("baudrate", 115200)),
                                         fmt=fmt, name=dev.name)  # fmt: skip
        bus = dev.get("bus", 1)
        if bus == "sim":
            if i2c_bus is None:
                raise UserInputError(
                    f"device '{dev.name}' is on the simulator's in-process I2C bus; run it in the same process"
                )
            bus = i2c_bus
        if dev.kind == "rm3100":
            return Rm3100(bus, int(dev.get("address")), name=dev.name)
        return Lis3mdl(bus, int(dev.get("address")), name=dev.name)
    except RegisterMapError as exc:
        raise UserInputError(str(exc)) from None


def build_cage(cfg: RigConfig, stack: ExitStack, i2c_bus: Any | None = None) -> CageController:
    """Open the cage's devices (closed by ``stack``) and build its controller.

    The controller's ``safe()`` is registered on ``stack`` first, so it runs on every exit path
    before the links close.
    """
    if cfg.cage is None:
        raise UserInputError(f"{cfg.path}: no [cage] section; add one to drive the cage")
    c = cfg.cage
    drives = []
    for name in c.axes:
        supply = open_device(cfg.devices[name], i2c_bus)
        stack.callback(supply.close)
        bipolar = bool(getattr(supply, "bipolar", False))

        def current(s: Any = supply) -> float:
            return abs(float(s.read().i_out_a))

        drives.append(
            AxisDrive(supply, bipolar, min(c.compliance_v, supply.max_voltage_v), current)
        )
    relays = None
    if c.polarity is not None:
        relays = open_device(cfg.devices[c.polarity], i2c_bus)
        stack.callback(relays.close)
    reference = None
    reference_to_cage = None
    if c.reference is not None:
        ref_cfg = cfg.devices[c.reference]
        reference = open_device(ref_cfg, i2c_bus)
        if hasattr(reference, "close"):
            stack.callback(reference.close)
        reference_to_cage = _reference_correction(cfg, ref_cfg)
    if c.calibration is not None and c.calibration.exists():
        model = CageModel.load(c.calibration)
    elif c.nominal_k_ut_per_a is not None:
        model = CageModel(np.array(c.nominal_k_ut_per_a), np.zeros(3), meta={"nominal": True})
    else:
        raise UserInputError(
            f"{cfg.path}: [cage] needs a calibration file or nominal_k_ut_per_a; characterize the cage first"
        )
    limits = CageLimits(c.max_current_a, c.max_field_ut, c.max_slew_a_per_s, c.step_s)
    controller = CageController(drives, model, limits, relays=relays, reference=reference,
                                reference_to_cage=reference_to_cage)  # fmt: skip
    stack.callback(controller.safe)
    return controller


def _reference_correction(
    cfg: RigConfig, dev: DeviceConfig
) -> tuple[np.ndarray, np.ndarray] | None:
    """The reference's certificate: ``h_cage = correction_matrix @ (m - correction_offset_ut)``."""
    matrix, offset = dev.get("correction_matrix"), dev.get("correction_offset_ut")
    if matrix is None and offset is None:
        return None
    try:
        m = np.eye(3) if matrix is None else np.array(matrix, float).reshape(3, 3)
        o = np.zeros(3) if offset is None else np.array(offset, float).reshape(3)
    except ValueError:
        raise UserInputError(
            f"{cfg.path}: [devices.{dev.name}] correction_matrix must be 3x3 and correction_offset_ut 3 numbers"
        ) from None
    return m, o
