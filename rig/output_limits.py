"""Every output's own limits, enforced where it is written, whatever role a procedure gives it.

A supply or load is opened through :func:`rig.devices.open_load` or :func:`rig.devices.build_cage`,
and both wrap the driver in a :class:`LimitedOutput` holding the device's :class:`OutputLimits`:

* its instrument range, narrowed by ``max_current_a`` / ``max_voltage_v`` in the rig configuration;
* for a cage coil supply (known by its wire address, :mod:`rig.wire_address`, never by its name:
  a second name for a coil supply has the coil's limits), also the cage's limits: ``[cage].max_current_a`` for its axis,
  ``[cage].compliance_v``, and the most current any field within ``[cage].max_field_ut`` needs on
  its axis (from the cage model), so no path drives a coil past what a legal field command could.

A set-point beyond a limit is **refused**, never capped: nothing is sent, and
:class:`OutputLimitError` (one line: device, value, limit and where the limit comes from) ends the
run with status ``error`` through the safe path. A capped set-point would silently run a different
experiment than the one written; a refused one cannot exceed the limit either.

An output with ``max_power_w`` also has a power limit (:func:`with_power_limit`): a current
set-point whose worst case ``|I| x V`` exceeds it is refused, ``V`` being the voltage the output
may reach (its voltage set-point, its compliance as a load, within its voltage limit; the voltage
limit itself while none was given, or for an electronic load, which has no voltage set-point),
and so is a voltage set-point that would raise the worst case beyond it (ADR 0035).

``rig check`` and ``rig run`` also refuse, before any output is on, a procedure that names a cage
coil supply, the polarity relays or the reference as a load (:func:`refuse_cage_devices_as_loads`);
the limits here are what holds if that check is bypassed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from drivers.identity import Identity
from drivers.protocols import ProtectionLevel, SupplyReading
from drivers.registry import KINDS
from rig.cage.model import CageModel
from rig.config import DeviceConfig, RigConfig
from rig.errors import RigError, UserInputError
from rig.wire_address import lock_addresses

TOLERANCE = 1e-9
"""Set-points this close above a limit count as at it (floating-point rounding)."""


class OutputLimitError(RigError):
    """A set-point beyond an output's own limit; nothing was sent to the device."""


@dataclass(frozen=True)
class OutputLimits:
    """The largest set-points an output may be given: current magnitude (A) and voltage (V), each
    with the words naming where the limit comes from (for the refusal message)."""

    device: str
    max_current_a: float
    current_from: str
    max_voltage_v: float | None = None
    voltage_from: str = ""
    max_power_w: float | None = None
    """The most power (W) the output may deliver, worst case ``|I| x V``; None: no limit."""
    power_from: str = ""


def cage_model(cfg: RigConfig) -> CageModel | None:
    """The cage model a rig configuration gives: its calibration file if there is one, else the
    nominal ``nominal_k_ut_per_a`` (B0 = 0); None without either (or without a cage)."""
    c = cfg.cage
    if c is None:
        return None
    if c.calibration is not None and c.calibration.exists():
        return CageModel.load(c.calibration)
    if c.nominal_k_ut_per_a is not None:
        return CageModel(np.array(c.nominal_k_ut_per_a), np.zeros(3), meta={"nominal": True})
    return None


def field_limit_current_a(model: CageModel, max_field_ut: float, axis: int) -> float:
    """The most current (A) axis ``axis`` needs for any field within ``max_field_ut`` (uT):
    ``I = K^-1 (B - B0)`` over ``|B| <= max_field_ut``, whose largest ``|I_axis|`` is
    ``max_field_ut * |row_axis(K^-1)| + |(K^-1 B0)_axis|``."""
    k_inv = np.linalg.inv(model.k_ut_per_a)
    row = k_inv[axis]
    return float(max_field_ut * np.linalg.norm(row) + abs(row @ model.b0_ut))


def output_limits(cfg: RigConfig | None, dev: DeviceConfig, driver: Any) -> OutputLimits:
    """The limits of output ``dev`` opened as ``driver``: its range and configured limits, and
    when ``cfg`` makes it a cage coil supply the cage's; the tightest one of each kind wins."""
    name = dev.name
    configured = dev.get("max_current_a")
    current = [
        (
            float(driver.max_current_a),
            f"max_current_a of [devices.{name}]"
            if configured is not None and float(configured) <= float(driver.max_current_a)
            else "the instrument's range",
        )
    ]
    volts_max = getattr(driver, "max_voltage_v", None)
    volts_configured = dev.get("max_voltage_v")
    voltage = [] if volts_max is None else [(float(volts_max), (
        f"max_voltage_v of [devices.{name}]"
        if volts_configured is not None and float(volts_configured) <= float(volts_max)
        else f"the voltage range of {name}"))]  # fmt: skip
    c = cfg.cage if cfg is not None else None
    axis = cage_axis(cfg, dev) if cfg is not None else None
    if cfg is not None and c is not None and axis is not None:
        current.append((c.max_current_a[axis], f"the cage's max_current_a for axis {'xyz'[axis]}"))
        voltage.append((c.compliance_v, "the cage's compliance_v"))
        model = cage_model(cfg)
        if model is not None:
            current.append(
                (
                    field_limit_current_a(model, c.max_field_ut, axis),
                    f"the most any field within the cage's {c.max_field_ut:g} uT limit needs"
                    f" on axis {'xyz'[axis]}",
                )
            )
    amps, amps_from = min(current, key=lambda x: x[0])
    volts, volts_from = min(voltage, key=lambda x: x[0]) if voltage else (None, "")
    return OutputLimits(name, amps, amps_from, volts, volts_from)


def with_power_limit(limits: OutputLimits, dev: DeviceConfig) -> OutputLimits:
    """``limits`` with the power limit of output ``dev`` (its ``max_power_w``, W), if it has one."""
    watts = dev.get("max_power_w")
    if watts is None:
        return limits
    return replace(limits, max_power_w=float(watts),
                   power_from=f"max_power_w of [devices.{dev.name}]")  # fmt: skip


class LimitedOutput:
    """A supply or load driver behind its :class:`OutputLimits`: every set-point goes through
    here, and one beyond a limit raises :class:`OutputLimitError` without reaching the device.
    Everything else (``read``, ``safe``, ``link``, ...) is the driver's own."""

    def __init__(self, driver: Any, limits: OutputLimits) -> None:
        self.driver = driver
        self.limits = limits
        self.name: str = driver.name
        self.current_set_a = 0.0
        """The last current set-point sent (A); 0 after :meth:`safe`."""
        self._volts_set: float | None = None  # the last voltage set-point sent (V)

    def __getattr__(self, attr: str) -> Any:
        return getattr(self.driver, attr)

    @property
    def max_current_a(self) -> float:
        """The largest current set-point magnitude this output accepts (A)."""
        return self.limits.max_current_a

    @property
    def max_voltage_v(self) -> float:
        """The largest voltage set-point this output accepts (V)."""
        own = float(self.driver.max_voltage_v)
        return own if self.limits.max_voltage_v is None else min(own, self.limits.max_voltage_v)

    @property
    def bipolar(self) -> bool:
        """True when the current set-point is signed."""
        return bool(getattr(self.driver, "bipolar", False))

    @property
    def sets_voltage(self) -> bool:
        """True when the output has a voltage set-point (an electronic load has none)."""
        return bool(getattr(self.driver, "sets_voltage", True))

    def reach_v(self, volts_set: float | None = None) -> float:
        """The most voltage (V) the output may put across its load with voltage set-point
        ``volts_set`` (None: the last one sent): that set-point within the voltage limit; the
        voltage limit itself before any was sent, or for an output without one."""
        volts = self._volts_set if volts_set is None else volts_set
        if volts is None or not self.sets_voltage:
            return self.max_voltage_v
        return min(volts, self.max_voltage_v)

    def _check_power(self, amps: float, volts_set: float | None, what: str) -> None:
        """Refuse (OutputLimitError) a worst case ``|amps| x V`` (W) beyond the power limit, V
        the voltage reached with set-point ``volts_set`` (:meth:`reach_v`)."""
        lim = self.limits
        if lim.max_power_w is None:
            return
        volts = self.reach_v(volts_set)
        watts = abs(amps) * volts
        if not watts <= lim.max_power_w * (1.0 + TOLERANCE) + TOLERANCE:  # also refuses NaN
            most = lim.max_power_w / volts if volts > 0 else math.inf
            raise OutputLimitError(
                f"{lim.device}: {what} makes a worst case of {abs(amps):g} A x {volts:g} V ="
                f" {watts:g} W, beyond its {lim.max_power_w:g} W limit ({lim.power_from});"
                f" nothing was sent: at {volts:g} V ask at most {most:.3g} A, or lower the"
                " voltage it may reach (compliance_v, max_voltage_v)"
            )

    def set_current(self, amps: float) -> float:
        """Current set-point (A), refused beyond the current or the power limit; returns what
        the driver set."""
        lim = self.limits
        if not abs(amps) <= lim.max_current_a + TOLERANCE:  # also refuses NaN
            raise OutputLimitError(
                f"{lim.device}: a set-point of {amps:g} A is beyond its {lim.max_current_a:g} A"
                f" limit ({lim.current_from}); nothing was sent: lower the current asked of it"
            )
        self._check_power(amps, None, f"a set-point of {amps:g} A")
        self.current_set_a = amps  # before it is sent: a write that fails may still have landed
        return float(self.driver.set_current(amps))

    def set_voltage(self, volts: float) -> float:
        """Voltage set-point (V), refused beyond the voltage limit or when the present current
        set-point would make a worst case beyond the power limit; returns what the driver set."""
        lim = self.limits
        if lim.max_voltage_v is not None and not volts <= lim.max_voltage_v + TOLERANCE:
            raise OutputLimitError(
                f"{lim.device}: a set-point of {volts:g} V is beyond its {lim.max_voltage_v:g} V"
                f" limit ({lim.voltage_from}); nothing was sent: lower the voltage asked of it"
            )
        self._check_power(self.current_set_a, volts,
                          f"a set-point of {volts:g} V at {self.current_set_a:g} A")  # fmt: skip
        done = float(self.driver.set_voltage(volts))
        self._volts_set = volts
        return done

    def enable_as_load(self, compliance_v: float) -> None:
        """As the driver's (current 0, voltage set-point at the compliance, output on), with the
        compliance voltage (V) within this output's voltage limit."""
        if self.limits.max_voltage_v is not None:
            compliance_v = min(compliance_v, self.limits.max_voltage_v)
        self.driver.enable_as_load(compliance_v)
        self.current_set_a = 0.0
        self._volts_set = compliance_v

    def set_output(self, on: bool) -> None:
        """Output enable."""
        self.driver.set_output(on)

    def read(self) -> SupplyReading:
        """The driver's read-back."""
        reading: SupplyReading = self.driver.read()
        return reading

    def identify(self) -> Identity:
        """The driver's identity."""
        ident: Identity = self.driver.identify()
        return ident

    def safe(self) -> None:
        """The driver's safe state (always allowed)."""
        self.driver.safe()
        self.current_set_a = 0.0

    def close(self) -> None:
        """Close the driver's link."""
        self.driver.close()


def limited(cfg: RigConfig | None, dev: DeviceConfig, driver: Any) -> LimitedOutput:
    """``driver`` (output ``dev``, of ``cfg`` if given) behind its limits."""
    return LimitedOutput(driver, with_power_limit(output_limits(cfg, dev, driver), dev))


def _named_at(cfg: RigConfig, dev: DeviceConfig, names: list[str | None]) -> int | None:
    """The index of the first of ``names`` that is ``dev`` by name, else the first that is on
    ``dev``'s wire address (:func:`rig.wire_address.lock_addresses`, ``dev``'s resolved once);
    None for none of them."""
    if dev.name in names:
        return names.index(dev.name)
    mine = set(lock_addresses(dev))
    for i, name in enumerate(names):
        other = cfg.devices.get(name) if name is not None else None
        if other is not None and mine & set(lock_addresses(other)):
            return i
    return None


def cage_axis(cfg: RigConfig, dev: DeviceConfig) -> int | None:
    """The cage axis (0-2) whose coil supply ``dev`` is on the wire, whatever name it is given
    (:func:`rig.wire_address.same_device`); None for any other device."""
    c = cfg.cage
    return None if c is None else _named_at(cfg, dev, list(c.axes))


def cage_role(cfg: RigConfig, name: str) -> str | None:
    """What device ``name`` is in the cage ("the cage's x coil supply", "the cage's polarity
    relays", "the cage's reference magnetometer"), None if it is not part of the cage. Keyed by
    the wire address: a second name for a cage device has its role ("... (coil_x, on the same
    address)")."""
    c = cfg.cage
    if c is None or name not in cfg.devices:
        return None
    roles: list[tuple[str | None, str]] = [
        (n, f"the cage's {'xyz'[i]} coil supply") for i, n in enumerate(c.axes)
    ]
    roles += [(c.polarity, "the cage's polarity relays"), (c.reference,
              "the cage's reference magnetometer"), (c.ambient,
              "the cage's outside reference magnetometer")]  # fmt: skip
    if c.trim is not None:
        roles += [(n, f"the cage's {'xyz'[i]} trim supply") for i, n in enumerate(c.trim)]
    found = _named_at(cfg, cfg.devices[name], [device for device, _ in roles])
    if found is None:
        return None
    device, role = roles[found]
    return role if device == name else f"{role} ({device}, on the same address)"


def refuse_cage_devices_as_loads(loads: list[str], cfg: RigConfig, procedure: Path) -> None:
    """Refuse (one line, UserInputError) a procedure whose ``loads:`` name a cage device: a coil
    is driven by field steps within the cage's limits, never as a load channel."""
    for name in loads:
        role = cage_role(cfg, name)
        if role is not None:
            channels = [n for n, d in cfg.devices.items() if d.kind in KINDS
                        and "load" in KINDS[d.kind].roles and cage_role(cfg, n) is None]  # fmt: skip
            raise UserInputError(
                f"{procedure}: loads: '{name}' is {role} in {cfg.path}; a cage device is never"
                f" a load (coils take field steps, within the cage limits): name a load channel"
                f" ({', '.join(channels) or 'none in the configuration'})"
            )


# --- protection levels: the instrument's own trip levels against the rig's limits ------------

PROTECTION_KEYS = {"OVP": "ovp_v", "OCP": "ocp_a", "OPP": "opp_w"}
"""The rig configuration's key for each protection level (written when the rig opens the output)."""


def protection_limits(dev: DeviceConfig, limits: OutputLimits, *, sets_voltage: bool,
                      cage_device: bool) -> dict[str, tuple[float, str]]:  # fmt: skip
    """The most each protection level of output ``dev`` may be, with the words naming where that
    limit comes from: OCP its current limit, OVP its voltage limit (for a load channel with a
    voltage set-point also its ``compliance_v``, the most the rig puts across its load), OPP its
    ``max_power_w``. A level with no finite limit is left out."""
    allowed = {"OCP": (limits.max_current_a, limits.current_from)}
    volts = [] if limits.max_voltage_v is None else [(limits.max_voltage_v, limits.voltage_from)]
    if sets_voltage and not cage_device:
        volts.append((float(dev.get("compliance_v", 12.0)),
                      f"compliance_v of [devices.{dev.name}]"))  # fmt: skip
    if volts:
        allowed["OVP"] = min(volts, key=lambda v: v[0])
    if limits.max_power_w is not None:
        allowed["OPP"] = (limits.max_power_w, limits.power_from)
    return {kind: v for kind, v in allowed.items() if math.isfinite(v[0])}


def protection_findings(dev: DeviceConfig, levels: tuple[ProtectionLevel, ...],
                        allowed: dict[str, tuple[float, str]]) -> list[str]:  # fmt: skip
    """One sentence per protection level looser than its limit (``allowed``, from
    :func:`protection_limits`): the output, the level, where it is, the limit and the fix."""
    found = []
    for level in levels:
        if level.kind not in allowed or level.value <= allowed[level.kind][0] * (1 + TOLERANCE):
            continue
        limit, source = allowed[level.kind]
        u, key = level.unit, PROTECTION_KEYS[level.kind]
        found.append(
            f"{dev.name}: {level.kind} is {level.value:g} {u} ({level.register}), above"
            f" {limit:g} {u}, {source}: the instrument would let the output pass the rig's limit"
            f" before it switches off; lower it to at most {limit:g} {u} ({key} = {limit:g} in"
            f" [devices.{dev.name}] is written when the rig opens it, or set it on the instrument)"
        )
    return found


class _NotOpened:
    """Output ``dev``'s instrument, not opened: no range of its own, only its configured limits."""

    def __init__(self, dev: DeviceConfig) -> None:
        self.max_current_a = float(dev.get("max_current_a", math.inf))
        self.max_voltage_v = float(dev.get("max_voltage_v", math.inf))


def configured_protection_findings(cfg: RigConfig) -> list[str]:
    """The protection levels the configuration gives (``ovp_v``, ``ocp_a``, ``opp_w``) that are
    looser than the same output's limits, one sentence each; no device is opened."""
    found = []
    for dev in cfg.devices.values():
        levels = tuple(ProtectionLevel(kind, float(dev.get(key)), f"{key} in [devices.{dev.name}]")
                       for kind, key in PROTECTION_KEYS.items() if dev.get(key) is not None)  # fmt: skip
        if not levels:
            continue
        limits = with_power_limit(output_limits(cfg, dev, _NotOpened(dev)), dev)
        allowed = protection_limits(dev, limits, sets_voltage=dev.kind != "regmap-eload",
                                    cage_device=cage_role(cfg, dev.name) is not None)  # fmt: skip
        found += protection_findings(dev, levels, allowed)
    return found
