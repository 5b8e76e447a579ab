"""The rig configuration for a simulated cage: its devices, the reference's certificate and the
coil constants as nameplate values (``rig sim --rig-config``, tests, benchmarks)."""

from __future__ import annotations

import contextlib
import json
import math
import re
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.registry import KINDS
from sim.config import MagnetometerConfig, SimConfig

if TYPE_CHECKING:
    from sim.cage import SimulatedCage

ENDPOINT_ONLY = frozenset({"role", "stopbits", "line_format", "unit"})
"""What the simulator's endpoints document says of a device that is no rig configuration key: its
role in the cage (read here for ``[cage]``), and line settings the drivers take as their defaults
(8N1, whitespace-separated columns in uT). :func:`device_lines` writes only declared keys."""
_XYZ = re.compile(r"\{x[^{}]*\}\s+\{y[^{}]*\}\s+\{z[^{}]*\}")


def rig_config_toml(
    endpoints: dict[str, Any],
    sim_config: str,
    nominal_k: list[list[float]] | None = None,
    trim_ut_per_a: list[float] | None = None,
    coil_tau_s: float | None = None,
) -> str:
    """A rig configuration (TOML) that points at the simulated devices.

    The [cage] section maps the coil supplies by their roles and uses the coil constants rounded to
    1 uT/A as the nameplate (nominal) model until the cage is characterized.
    """
    lines = [
        "# Rig configuration written by `rig sim`: the devices of the simulated cage.",
        f"# simulator configuration: {sim_config}",
        "",
    ]
    devices = endpoints["devices"]
    roles = {dev.get("role"): name for name, dev in devices.items()}
    if all(f"coil_{ax}" in roles for ax in "xyz"):
        reference = roles.get("reference") or next(
            (n for n, d in devices.items() if d["kind"] == "ascii-mag" and "role" not in d), None
        )
        lines += [
            "[cage]",
            "axes = { " + ", ".join(f'{ax} = "{roles[f"coil_{ax}"]}"' for ax in "xyz") + " }",
        ]
        if "polarity" in roles:
            lines.append(f'polarity = "{roles["polarity"]}"')
        if reference:
            lines.append(f'reference = "{reference}"')
        if "ambient" in roles:
            lines.append(f'ambient = "{roles["ambient"]}"')
        if "scalar" in roles:
            lines.append(f'scalar = "{roles["scalar"]}"')
        if trim_ut_per_a is not None and all(f"trim_{ax}" in roles for ax in "xyz"):
            lines.append("trim = { " + ", ".join(f'{ax} = "{roles[f"trim_{ax}"]}"' for ax in "xyz")
                         + " }")  # fmt: skip
            lines.append(f"trim_ut_per_a = {json.dumps([round(v, 1) for v in trim_ut_per_a])}")
        lines += [*_cage_limits(coil_tau_s, nominal_k), ""]
    for name, dev in endpoints["devices"].items():
        lines += device_lines(name, dev)
    return "\n".join(lines)


def _cage_limits(coil_tau_s: float | None, nominal_k: list[list[float]] | None) -> list[str]:
    """The simulated cage's ``[cage]`` limits, its coils' L/R and nameplate coil constants."""
    lines = [
        'calibration = "cage-calibration.json"',
        "max_current_a = [2.5, 2.5, 2.5]",
        "max_field_ut = 120.0",
        "max_ambient_ut = 55.0  # the simulated lab field is 49 uT",
        "max_slew_a_per_s = 10.0",
        "compliance_v = 12.0",
    ]
    if coil_tau_s is not None:
        lines.append(f"coil_tau_s = {coil_tau_s:.4g}  # the coils' nameplate L/R")
    if nominal_k is not None:
        rows = ", ".join("[" + ", ".join(f"{round(v):.1f}" for v in row) + "]" for row in nominal_k)
        lines.append(f"nominal_k_ut_per_a = [{rows}]")
    return lines


def _toml_value(value: Any) -> str:
    if isinstance(value, list):
        return json.dumps(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return str(value)
    return json.dumps(str(value))


def device_lines(name: str, dev: dict[str, Any]) -> list[str]:
    """The ``[devices.NAME]`` table of one simulated device: ``kind``, ``protocol`` and the keys
    its kind declares (:mod:`drivers.registry`); the endpoint's own entries (:data:`ENDPOINT_ONLY`)
    are left out, anything else undeclared is a mistake here."""
    declared = {p.name for p in KINDS[dev["kind"]].param_specs(dev["protocol"])}
    unknown = set(dev) - declared - ENDPOINT_ONLY - {"kind", "protocol"}
    if unknown:
        raise ValueError(f"simulated device '{name}': no rig configuration key {sorted(unknown)}")
    fmt = str(dev.get("line_format", "{x} {y} {z}"))
    if dev.get("unit", "uT") != "uT" or dev.get("stopbits", 1) != 1 or not _XYZ.fullmatch(fmt):
        raise ValueError(f"simulated device '{name}': its line settings are not the drivers'"
                         " defaults (8N1; x, y, z in uT separated by whitespace)")  # fmt: skip
    keys = [k for k in dev if k in declared or k in ("kind", "protocol")]
    return [f"[devices.{name}]", *(f"{k} = {_toml_value(dev[k])}" for k in keys), ""]


def reference_certificate(mag: MagnetometerConfig, seed: int = 0) -> dict[str, Any]:
    """The reference magnetometer's calibration certificate (``h = correction_matrix @ (m -
    correction_offset_ut)``): its truth off by an error drawn (seeded by ``seed`` and the name)
    within the 1-sigma it states, as a real certificate is; exact, and saying so to print
    precision, when the simulator gives it no sigma."""
    from sim.physics import rotation_matrix, springmann_matrix

    rng = np.random.default_rng([seed, zlib.crc32(mag.name.encode())])
    scale_sigma = mag.certificate_scale_sigma
    angle_sigma, mount_sigma = (math.radians(s / 3600.0) for s in (
        mag.certificate_angle_sigma_arcsec, mag.certificate_mounting_sigma_arcsec))  # fmt: skip
    scale = np.array(mag.scale) * (1.0 + scale_sigma * rng.standard_normal(3))
    nonorth = np.radians(np.array(mag.nonorth_deg)) + angle_sigma * rng.standard_normal(3)
    mounting = np.radians(np.array(mag.mounting_deg)) + mount_sigma * rng.standard_normal(3)
    t = springmann_matrix(tuple(scale), tuple(nonorth)) @ rotation_matrix(mounting)
    return {
        "correction_matrix": np.linalg.inv(t).tolist(),
        "correction_offset_ut": [float(v) for v in mag.offset_ut],
        "correction_scale_sigma": scale_sigma or 1e-6,
        "correction_angle_sigma_arcsec": mag.certificate_angle_sigma_arcsec or 0.2,
        "correction_mounting_sigma_arcsec": mag.certificate_mounting_sigma_arcsec or 0.2,
    }


HEATER_COMPLIANCE_V = 10.0
"""The simulated heater pad's supply voltage as a load (V): 2.5 A into its 4 ohm, and with
:data:`HEATER_MAX_POWER_W` a worst case of 2 A."""
HEATER_MAX_POWER_W = 20.0
"""The simulated heater's power limit (W): 2 A into 4 ohm is 16 W, +32 K at 2 K/W."""
DUT_MAX_TEMPERATURE_C = 70.0
"""The simulated DUT's temperature limit (C), its thermometer the interlock (ADR 0035)."""


def heater_limits(devices: dict[str, dict[str, Any]], cfg: SimConfig) -> None:
    """Give the simulated heater (``[thermal].heater``) and the DUT's thermometer their limits
    and the heater its warming as a nameplate would state it (ADR 0035): ``heats``,
    ``kelvin_per_w``, ``thermal_tau_s``, ``resistance_ohm``; the thermometer
    ``max_temperature_c`` and the ambient the simulated DUT rests at."""
    thermal, thermometer = cfg.thermal, cfg.thermometer
    if thermal is None or thermometer is None:
        return
    if thermal.heater not in devices or thermometer.name not in devices:
        return
    resistance = next(s.resistance_ohm for s in cfg.supplies if s.name == thermal.heater)
    devices[thermal.heater] |= {
        "compliance_v": HEATER_COMPLIANCE_V, "max_power_w": HEATER_MAX_POWER_W,
        "heats": thermometer.name, "kelvin_per_w": round(thermal.k_per_w, 2),
        "thermal_tau_s": round(thermal.tau_s, 1), "resistance_ohm": resistance,
    }  # fmt: skip
    devices[thermometer.name] |= {"max_temperature_c": DUT_MAX_TEMPERATURE_C,
                                  "ambient_c": thermal.ambient_c}  # fmt: skip


SIM_PROCESS_STALL_AFTER_S = 5.0
"""``stall_after_s`` of the magnetometers of a ``rig sim`` process on the wall clock (s): its
instruments share this computer's cores with the rig (a real one has its own processor), and beside
CPU hogs and a full test run one went 2.0 s without streaming while the rig itself waited 0.2 s
for a CPU. In simulated time no instrument waits for a CPU and the default 1.5 s stands."""


def sim_rig_config(endpoints: dict[str, Any], cfg: SimConfig,
                   stall_after_s: float | None = None) -> str:  # fmt: skip
    """The rig configuration for a running simulated cage: devices, cage section, the reference's
    certificate and the coil constants as nameplate values; ``stall_after_s`` given to every
    magnetometer that takes it (None: its default)."""
    devices = {name: dict(dev) for name, dev in endpoints["devices"].items()}
    if stall_after_s is not None:
        for dev in devices.values():
            if any(
                p.name == "stall_after_s" for p in KINDS[dev["kind"]].param_specs(dev["protocol"])
            ):
                dev["stall_after_s"] = stall_after_s
    for mag in cfg.magnetometers:
        if mag.name in devices and mag.noise_ut > 0 and mag.kind != "geometrics-cm201":
            devices[mag.name]["noise_nt"] = round(1e3 * mag.noise_ut, 3)  # its datasheet's
        if mag.name in devices and mag.role == "reference" and mag.response_tau_s > 0:
            devices[mag.name]["response_tau_s"] = mag.response_tau_s  # its certificate's
        if mag.name in devices and mag.role == "reference" and mag.response_integration_s > 0:
            devices[mag.name]["response_integration_s"] = mag.response_integration_s
        if mag.name in devices and any(mag.position_m):
            devices[mag.name]["position_m"] = [float(v) for v in mag.position_m]
        if mag.kind == "ascii-mag" and mag.name in devices:
            devices[mag.name] |= reference_certificate(mag, cfg.seed)
            devices[mag.name]["rate_hz"] = mag.rate_hz
        elif mag.name in devices:
            devices[mag.name]["rate_hz"] = mag.rate_hz
    heater_limits(devices, cfg)
    nominal = [[float(v) for v in row] for row in cfg.cage.coil_matrix_ut_per_a]
    trims = [float(v) for v in cfg.cage.trim_ut_per_a] if any(cfg.cage.trim_ut_per_a) else None
    coil_tau_s = min(inductance / resistance for inductance, resistance
                     in zip(cfg.cage.inductance_h, cfg.cage.resistance_ohm, strict=True))  # fmt: skip
    return rig_config_toml({"devices": devices}, cfg.source, nominal, trims, coil_tau_s)


@contextlib.contextmanager
def cage_in_process(rig_toml: Path, sim_config: Path | None = None) -> Iterator[SimulatedCage]:
    """The simulated cage of ``sim_config`` (default: the built-in cage) started in this process
    on the current clock (in simulated time: on its wires, ADR 0038), with ``rig_toml`` written
    to open it; stopped on leaving."""
    from sim.cage import SimulatedCage
    from sim.config import load_config

    cfg = load_config(sim_config) if sim_config is not None else load_config()

    with SimulatedCage(cfg) as cage:
        rig_toml.write_text(sim_rig_config(cage.endpoints_document(), cfg), encoding="utf-8")
        yield cage
