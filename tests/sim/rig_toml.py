"""A rig configuration (TOML) for a running simulated cage, written here so that these tests do not
depend on how the CLI writes one."""

from __future__ import annotations

import json
from typing import Any

NOT_CONFIG_KEYS = ("role", "stopbits", "line_format", "unit")
"""Endpoint entries that are no rig configuration keys (unknown keys are refused)."""


LIMITS: dict[str, dict[str, Any]] = {
    "heater": {"compliance_v": 10.0, "max_power_w": 20.0, "heats": "dut_temp",
               "kelvin_per_w": 2.0, "thermal_tau_s": 120.0, "resistance_ohm": 4.0},
    "dut_temp": {"max_temperature_c": 70.0},
}  # fmt: skip
"""The default cage's heater (4 ohm, 2 K/W, 120 s) and DUT limits, as a nameplate states them."""


def rig_toml(endpoints: dict[str, Any], nominal_k: list[list[float]]) -> str:
    """The cage section (coil supplies by role, relays, the ASCII reference, nominal constants)
    and one ``[devices.NAME]`` table per simulated device."""
    devices = endpoints["devices"]
    roles = {dev.get("role"): name for name, dev in devices.items()}
    reference = next(n for n, d in devices.items() if d["kind"] == "ascii-mag")
    lines = [
        "[cage]",
        "axes = { " + ", ".join(f'{ax} = "{roles[f"coil_{ax}"]}"' for ax in "xyz") + " }",
        f'polarity = "{roles["polarity"]}"',
        f'reference = "{reference}"',
        "max_current_a = [2.5, 2.5, 2.5]",
        "max_field_ut = 120.0",
        "max_slew_a_per_s = 10.0",
        "compliance_v = 12.0",
        "nominal_k_ut_per_a = " + json.dumps([[round(v) for v in row] for row in nominal_k]),
        "",
    ]
    for name, dev in devices.items():
        lines.append(f"[devices.{name}]")
        lines += [f"{key} = {json.dumps(value)}" for key, value in dev.items()
                  if key not in NOT_CONFIG_KEYS]  # fmt: skip
        lines += [f"{key} = {json.dumps(value)}" for key, value in LIMITS.get(name, {}).items()]
        lines.append("")
    return "\n".join(lines)
