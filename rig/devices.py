"""Open drivers from the rig configuration, and build the cage controller from them."""

from __future__ import annotations

import contextlib
from contextlib import ExitStack
from typing import Any

import numpy as np

from drivers.errors import DeviceError
from drivers.protocols import (
    Load,
    Magnetometer,
    Protected,
    Relay,
    ScalarMagnetometer,
    Supply,
    Thermometer,
)
from drivers.registry import KINDS, OpenSpec, Role
from regmaps import RegisterMapError
from rig.cage.controller import AxisDrive, CageController
from rig.cage.limits import CageLimits
from rig.config import DeviceConfig, RigConfig
from rig.errors import UserInputError
from rig.output_limits import (
    PROTECTION_KEYS,
    cage_model,
    cage_role,
    limited,
    protection_findings,
    protection_limits,
)


def open_device(dev: DeviceConfig, i2c_bus: Any | None = None) -> Any:
    """A driver for ``dev``, opened by its kind's entry in :mod:`drivers.registry`.

    ``i2c_bus`` stands in for ``bus = "sim"`` (the simulator's bus). Prefer the typed openers
    (:func:`open_supply`, :func:`open_load`, :func:`open_relay`, :func:`open_magnetometer`).
    """
    kind = KINDS.get(dev.kind)
    if kind is None:  # a DeviceConfig made by hand, not by load_rig_config
        raise UserInputError(
            f"device '{dev.name}': kind '{dev.kind}' is not one of {', '.join(KINDS)}"
        )
    bus = None
    if dev.protocol == "i2c" and dev.get("bus", 1) == "sim":
        if i2c_bus is None:
            raise UserInputError(
                f"device '{dev.name}' is on the simulator's in-process I2C bus; run it in the same process"
            )
        bus = i2c_bus
    try:
        return kind.open(OpenSpec(dev.name, dev.protocol, dev.params, bus))
    except (RegisterMapError, ValueError) as exc:
        raise UserInputError(f"device '{dev.name}': {exc}") from None


def _check_role(dev: DeviceConfig, role: Role) -> None:
    kind = KINDS.get(dev.kind)
    if kind is not None and role not in kind.roles:
        raise UserInputError(
            f"device '{dev.name}' ({dev.kind}) cannot be used as a {role}; kinds that can: "
            + ", ".join(k for k, v in KINDS.items() if role in v.roles)
        )


def open_supply(
    dev: DeviceConfig, i2c_bus: Any | None = None, cfg: RigConfig | None = None
) -> Supply:
    """A coil supply (a kind with the ``supply`` role) behind its limits
    (:mod:`rig.output_limits`; with ``cfg``, the cage's too if it is a cage coil)."""
    _check_role(dev, "supply")
    supply: Supply = limited(cfg, dev, open_device(dev, i2c_bus))
    try:
        apply_protection_levels(dev, supply)
    except BaseException:
        supply.close()
        raise
    return supply


def apply_protection_levels(dev: DeviceConfig, output: object) -> None:
    """Write the protection levels ``dev`` gives (``ovp_v``, ``ocp_a``, ``opp_w``) to the opened
    ``output`` and read them back (the driver raises when one does not read back); a
    UserInputError for an instrument without protection levels the rig can set."""
    asked = {
        key: float(dev.get(key)) for key in PROTECTION_KEYS.values() if dev.get(key) is not None
    }
    if not asked:
        return
    if not isinstance(output, Protected):
        raise UserInputError(f"device '{dev.name}' ({dev.kind}) has no protection levels the rig"
                             f" can set; remove {', '.join(asked)} from its table")  # fmt: skip
    output.set_protection_levels(**asked)


def open_relay(dev: DeviceConfig, i2c_bus: Any | None = None) -> Relay:
    """A polarity relay board (a kind with the ``relay`` role)."""
    _check_role(dev, "relay")
    relay: Relay = open_device(dev, i2c_bus)
    return relay


def open_magnetometer(dev: DeviceConfig, i2c_bus: Any | None = None) -> Magnetometer:
    """A magnetometer (a kind with the ``magnetometer`` role)."""
    _check_role(dev, "magnetometer")
    mag: Magnetometer = open_device(dev, i2c_bus)
    return mag


def open_scalar_magnetometer(dev: DeviceConfig) -> ScalarMagnetometer:
    """A total-field magnetometer (a kind with the ``scalar`` role)."""
    _check_role(dev, "scalar")
    scalar: ScalarMagnetometer = open_device(dev, None)
    return scalar


def open_thermometer(dev: DeviceConfig, i2c_bus: Any | None = None) -> Thermometer:
    """A thermometer (a kind with the ``thermometer`` role)."""
    _check_role(dev, "thermometer")
    thermometer: Thermometer = open_device(dev, i2c_bus)
    return thermometer


def thermometer_names(cfg: RigConfig) -> list[str]:
    """The rig's thermometers (devices of a kind with the ``thermometer`` role), in file order:
    every run records each of them."""
    return [
        n
        for n, d in cfg.devices.items()
        if d.kind in KINDS and "thermometer" in KINDS[d.kind].roles
    ]


def open_load(dev: DeviceConfig, i2c_bus: Any | None = None, cfg: RigConfig | None = None) -> Load:
    """A load-current channel behind its limits (:mod:`rig.output_limits`; with ``cfg``, a cage
    coil supply keeps the cage's limits in this role too), ready to drive: current 0, its voltage
    set-point at the device's ``compliance_v`` (12 V when not given) where it has one, output
    on. If preparing fails the output is made safe and the link closed before the error
    propagates."""
    _check_role(dev, "load")
    load: Load = limited(cfg, dev, open_device(dev, i2c_bus))
    try:
        apply_protection_levels(dev, load)
        load.enable_as_load(float(dev.get("compliance_v", 12.0)))
    except BaseException:
        with contextlib.suppress(Exception):
            load.safe()
        load.close()
        raise
    return load


def build_cage(
    cfg: RigConfig, stack: ExitStack, i2c_bus: Any | None = None, *, safe_on_exit: bool = True
) -> CageController:
    """Open the cage's devices (closed by ``stack``) and build its controller.

    The controller's ``safe()`` is registered on ``stack`` first, so it runs on every exit path
    before the links close; not with ``safe_on_exit=False``: a ``RigSession`` takes its outputs
    safe itself (ADR 0012).
    """
    if cfg.cage is None:
        raise UserInputError(f"{cfg.path}: no [cage] section; add one to drive the cage")
    c = cfg.cage
    drives = []
    for name in c.axes:
        supply = open_supply(cfg.devices[name], i2c_bus, cfg)
        stack.callback(supply.close)
        bipolar = supply.bipolar

        def current(s: Supply = supply) -> float:
            return abs(float(s.read().i_out_a))

        drives.append(
            AxisDrive(supply, bipolar, min(c.compliance_v, supply.max_voltage_v), current)
        )
    relays = None
    if c.polarity is not None:
        relays = open_relay(cfg.devices[c.polarity], i2c_bus)
        stack.callback(relays.close)
    reference = None
    reference_to_cage = None
    if c.reference is not None:
        ref_cfg = cfg.devices[c.reference]
        reference = open_magnetometer(ref_cfg, i2c_bus)
        stack.callback(reference.close)
        reference_to_cage = _reference_correction(cfg, ref_cfg)
    model = cage_model(cfg)
    if model is None:
        raise UserInputError(
            f"{cfg.path}: [cage] needs a calibration file or nominal_k_ut_per_a; characterize the cage first"
        )
    limits = CageLimits(c.max_current_a, c.max_field_ut, c.max_slew_a_per_s, c.step_s, c.coil_tau_s)
    controller = CageController(drives, model, limits, relays=relays, reference=reference,
                                reference_to_cage=reference_to_cage)  # fmt: skip
    if safe_on_exit:
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


def instrument_protection_findings(
    cfg: RigConfig, i2c_bus: Any | None = None
) -> tuple[list[str], list[str]]:
    """Every supply's and load's protection levels, read from the instrument (opened as a run
    opens it, nothing switched) and held against its limits in ``cfg``
    (:func:`rig.output_limits.protection_findings`): the findings, and one sentence per output
    whose levels could not be read."""
    findings: list[str] = []
    unread: list[str] = []
    for dev in cfg.devices.values():
        kind = KINDS.get(dev.kind)
        if kind is None or not {"supply", "load"} & kind.roles:
            continue
        try:
            output = limited(cfg, dev, open_device(dev, i2c_bus))
        except (DeviceError, UserInputError) as exc:
            unread.append(f"{dev.name}: its protection levels were not read ({exc})")
            continue
        try:
            if not isinstance(output, Protected):
                unread.append(f"{dev.name}: {dev.kind} has no protection levels the rig can read")
                continue
            allowed = protection_limits(dev, output.limits, sets_voltage=output.sets_voltage,
                                        cage_device=cage_role(cfg, dev.name) is not None)  # fmt: skip
            findings += protection_findings(dev, output.protection_levels(), allowed)
        except DeviceError as exc:
            unread.append(f"{dev.name}: its protection levels were not read ({exc})")
        finally:
            output.close()
    return findings, unread
