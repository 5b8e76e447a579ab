"""The small spacecraft the closed-loop tests on the simulated cage detumble (10 deg/s in an orbit
replayed 30 times faster: below 4 deg/s in about a minute), and the designed calibration fields
they fit before a loop that reads calibrated, as procedure YAML."""

from __future__ import annotations

import json
from typing import Any

TLE = [
    "1 25544U 98067A   19343.69339541  .00001764  00000-0  38792-4 0  9991",
    "2 25544  51.6439 211.2001 0007417  17.6667  85.6398 15.50103472202482",
]
LOOP: dict[str, Any] = {
    "tle": TLE, "start": "2019-12-09T12:00:00Z", "time_scale": 30, "duration_s": 150,
    "rate_hz": 10, "control_hz": 2, "inertia_kg_m2": [0.001, 0.001, 0.0008],
    "max_dipole_am2": 0.2, "rate_deg_s": [5.77, 5.77, 5.77], "until_deg_s": 4,
}  # fmt: skip
FIELDS = [[44.5, -5.27, -4.12], [39.13, -19.78, -10.13], [43.75, 10.35, 1.87],
          [22.72, 27.56, -27.38], [-12.21, 25.68, -34.87], [-0.81, -9.97, -43.88],
          [12.68, -11.47, -41.62], [-25.26, -21.55, -30.38], [-28.4, -31.69, -14.62],
          [-44.91, -2.57, -1.12], [-43.61, 7.01, 8.62], [-23.04, 31.7, 22.12],
          [-2.28, 36.75, 25.87], [16.37, 29.65, 29.62], [-6.49, 44.53, 0.37],
          [0.48, -23.08, 38.62], [-10.03, -29.33, 32.62], [15.76, -23.67, 34.88],
          [4.44, -42.81, 13.12]]  # fmt: skip
"""The 19 field set-points rig design chose for the built-in cage (rig/shipped_procedures/
dut-acceptance-designed.yaml)."""


def loop_step(name: str, **changes: Any) -> str:
    """A ``closed_loop`` step (YAML, as an item under ``steps:``) of :data:`LOOP` with
    ``changes``."""
    body = "\n".join(f"      {k}: {json.dumps(v)}" for k, v in {**LOOP, **changes}.items())
    return f"  - closed_loop:\n{body}\n    name: {name}\n"


def calibration_steps(loads: bool) -> str:
    """The :data:`FIELDS` (with step profiles on load_bus and load_panel when ``loads``) and a
    vector calibration of them named ``calibration`` (YAML items under ``steps:``)."""
    profiles = (
        "    loads:\n"
        "      load_bus: {steps: {levels_a: [0, 0.8, 1.6], dwell_s: 2.4}}\n"
        "      load_panel: {steps: {levels_a: [0, 1, 2, 2.5], dwell_s: 3.2}}\n"
    )
    telemetry = ", telemetry: [load_bus, load_panel]" if loads else ""
    return (
        f"  - field_points: {{dwell_s: 0.8, fields_ut: {json.dumps(FIELDS)}}}\n"
        "    name: fields\n" + (profiles if loads else "")
        + f"  - calibrate: {{model: vector{telemetry}, steps: [fields]}}\n"
        "    name: calibration\n"
    )  # fmt: skip
