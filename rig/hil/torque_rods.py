"""Torque rods through the rig's loads: each body axis's commanded dipole as a load channel's
current, so the rods' stray field reaches the DUT as it would on the spacecraft.

A load sinks current in one direction only, so a rod's current is ``bias_a + dipole *
a_per_am2`` (A): ``bias_a`` at zero dipole, 0 and ``2 bias_a`` at the rod's largest dipole
either way (``bias_a`` must be at least ``max_dipole_am2 * a_per_am2``). The bias's stray field is
a constant offset B-dot does not see (it differentiates); the part that follows the dipole is what
a flight magnetometer beside real rods sees. With ``readings: calibrated`` the loop subtracts each
channel's fitted current-to-bias coefficient times its current, as flight software that knows
its rods' currents would: how well the rig fitted those coefficients then shows in the loop.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

NO_ROD = "none"
"""In ``torque_rods``: the axis has no rod on a load."""


@dataclass(frozen=True)
class TorqueRods:
    """``channels``: the load channel of the x, y and z rod (None: no rod on a load);
    ``a_per_am2``: the rod current per dipole (A per A m^2); ``bias_a``: its current at zero
    dipole (A)."""

    channels: tuple[str | None, str | None, str | None]
    a_per_am2: float
    bias_a: float

    @staticmethod
    def of(params: dict[str, Any]) -> TorqueRods | None:
        """The rods a closed-loop step's parameters name; None without any."""
        names = list(params.get("torque_rods") or [])
        if not names:
            return None
        c = [None if n == NO_ROD else str(n) for n in names]
        return TorqueRods((c[0], c[1], c[2]), float(params["rod_a_per_am2"]),
                          float(params["rod_bias_a"]))  # fmt: skip

    @property
    def used(self) -> tuple[str, ...]:
        return tuple(c for c in self.channels if c is not None)

    def currents_a(self, dipole_am2: Sequence[float] | Array) -> dict[str, float]:
        """Each rod channel's current (A) for the body dipole (A m^2), never below 0 A."""
        return {ch: max(0.0, self.bias_a + float(d) * self.a_per_am2)
                for ch, d in zip(self.channels, dipole_am2, strict=True) if ch is not None}  # fmt: skip

    def peak_a(self, max_dipole_am2: float) -> dict[str, float]:
        """Each rod channel's largest current (A): at the rod's largest dipole."""
        return {ch: self.bias_a + max_dipole_am2 * self.a_per_am2 for ch in self.used}


def rods_problem(params: dict[str, Any], loads: tuple[str, ...]) -> str | None:
    """What is wrong with a closed-loop step's rods, or None (``loads``: the procedure's load
    channels)."""
    names = list(params.get("torque_rods") or [])
    if not names:
        return None
    if len(names) != 3:
        return (f"'torque_rods' names the x, y and z rods' load channels (three names, '{NO_ROD}'"
                f" for an axis without one), not {len(names)}")  # fmt: skip
    used = [n for n in names if n != NO_ROD]
    if not used:
        return f"'torque_rods' names no load channel (all '{NO_ROD}')"
    if len(set(used)) != len(used):
        return "'torque_rods' names a load channel twice: one rod per channel"
    missing = [n for n in used if n not in loads]
    if missing:
        return (f"torque rod channel {missing[0]!r} is not one of the procedure's loads"
                f" {list(loads)} (add it under 'loads:')")  # fmt: skip
    scale, bias = float(params["rod_a_per_am2"]), float(params["rod_bias_a"])
    if scale <= 0:
        return "'rod_a_per_am2' (the rod current per dipole, A per A m^2) must be > 0 with rods"
    need = float(params["max_dipole_am2"]) * scale
    if bias < need:
        return (f"'rod_bias_a' {bias:g} A is below the {need:g} A a rod's largest dipole takes"
                " from it (max_dipole_am2 x rod_a_per_am2): a load cannot sink a negative current")  # fmt: skip
    return None


@dataclass
class RodLog:
    """The rods' currents as commanded, by when (monotonic s): what the DUT's reading at a time
    had beside it."""

    times_s: list[float] = field(default_factory=list)
    currents_a: list[dict[str, float]] = field(default_factory=list)

    def add(self, t_s: float, currents_a: dict[str, float]) -> None:
        self.times_s.append(t_s)
        self.currents_a.append(dict(currents_a))

    def at(self, t_s: float) -> dict[str, float]:
        """The currents commanded last at or before ``t_s`` (empty before the first)."""
        i = bisect.bisect_right(self.times_s, t_s)
        return self.currents_a[i - 1] if i else {}


def stray_bias_ut(k_ut_per_a: dict[str, Array], currents_a: dict[str, float]) -> Array:
    """The loads' bias on the DUT (uT, its frame): each channel's coefficient times its current."""
    total = np.zeros(3)
    for ch, k in k_ut_per_a.items():
        total = total + np.asarray(k, float) * float(currents_a.get(ch, 0.0))
    return total
