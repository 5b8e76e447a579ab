"""Protection levels asked of a supply or load, written and read back: what the drivers share."""

from __future__ import annotations

import math

from drivers.errors import DeviceProtocolError, LimitError
from drivers.protocols import PROTECTION_UNITS, ProtectionLevel


def asked_levels(device: str, *, ovp_v: float | None, ocp_a: float | None,
                 opp_w: float | None) -> dict[str, float]:  # fmt: skip
    """The levels asked for by kind ("OVP", "OCP", "OPP"); LimitError for one that is not a
    finite number above 0 (a level of 0 trips the output at once)."""
    asked = {"OVP": ovp_v, "OCP": ocp_a, "OPP": opp_w}
    levels = {kind: float(value) for kind, value in asked.items() if value is not None}
    for kind, value in levels.items():
        if not (math.isfinite(value) and value > 0.0):
            raise LimitError(
                f"{device}: {kind} {value:g} {PROTECTION_UNITS[kind]} is not a level above 0;"
                " give the level the output must not pass"
            )
    return levels


def check_read_back(device: str, asked: dict[str, tuple[float, float]],
                    levels: tuple[ProtectionLevel, ...]) -> None:  # fmt: skip
    """DeviceProtocolError naming the register when a level written (``asked``: kind -> (value,
    resolution of its register)) reads back more than half a count away from it."""
    read = {level.kind: level for level in levels}
    for kind, (value, resolution) in asked.items():
        got = read[kind]
        if abs(got.value - value) > resolution / 2 + 1e-12:
            raise DeviceProtocolError(
                f"{device}: {kind} written as {value:g} {got.unit} reads back {got.value:g}"
                f" {got.unit} ({got.register}); the instrument did not take it: check that it is"
                " in remote mode and not locked, and the register map's scale"
            )
