"""``rig sim``: run the simulated cage as a standalone process until Ctrl-C or SIGTERM."""

from __future__ import annotations

import json
import math
import signal
import threading
import time
from pathlib import Path
from types import FrameType
from typing import Any

import numpy as np

from rig.errors import UserInputError
from sim.config import MagnetometerConfig, SimConfig


def rig_config_toml(
    endpoints: dict[str, Any], sim_config: str, nominal_k: list[list[float]] | None = None
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
        reference = next((n for n, d in devices.items() if d["kind"] == "ascii-mag"), None)
        lines += [
            "[cage]",
            "axes = { " + ", ".join(f'{ax} = "{roles[f"coil_{ax}"]}"' for ax in "xyz") + " }",
        ]
        if "polarity" in roles:
            lines.append(f'polarity = "{roles["polarity"]}"')
        if reference:
            lines.append(f'reference = "{reference}"')
        lines += [
            'calibration = "cage-calibration.json"',
            "max_current_a = [2.5, 2.5, 2.5]",
            "max_field_ut = 120.0",
            "max_slew_a_per_s = 10.0",
            "compliance_v = 12.0",
        ]
        if nominal_k is not None:
            rows = ", ".join(
                "[" + ", ".join(f"{round(v):.1f}" for v in row) + "]" for row in nominal_k
            )
            lines.append(f"nominal_k_ut_per_a = [{rows}]")
        lines.append("")
    for name, dev in endpoints["devices"].items():
        lines.append(f"[devices.{name}]")
        for key, value in dev.items():
            if isinstance(value, list):
                lines.append(f"{key} = {json.dumps(value)}")
            elif isinstance(value, bool):
                lines.append(f"{key} = {'true' if value else 'false'}")
            elif isinstance(value, int | float):
                lines.append(f"{key} = {value}")
            else:
                lines.append(f"{key} = {json.dumps(str(value))}")
        lines.append("")
    return "\n".join(lines)


def reference_certificate(mag: MagnetometerConfig) -> dict[str, Any]:
    """The reference magnetometer's calibration certificate: its small errors are known, as a
    calibrated fluxgate's are (``h = correction_matrix @ (m - correction_offset_ut)``)."""
    from sim.physics import rotation_matrix, springmann_matrix

    t = springmann_matrix(mag.scale, tuple(math.radians(v) for v in mag.nonorth_deg))
    t = t @ rotation_matrix(np.radians(np.array(mag.mounting_deg)))
    return {
        "correction_matrix": np.linalg.inv(t).tolist(),
        "correction_offset_ut": [float(v) for v in mag.offset_ut],
    }


def sim_rig_config(endpoints: dict[str, Any], cfg: SimConfig) -> str:
    """The rig configuration for a running simulated cage: devices, cage section, the reference's
    certificate and the coil constants as nameplate values."""
    devices = {name: dict(dev) for name, dev in endpoints["devices"].items()}
    for mag in cfg.magnetometers:
        if mag.kind == "ascii-mag" and mag.name in devices:
            devices[mag.name] |= reference_certificate(mag)
            devices[mag.name]["rate_hz"] = mag.rate_hz
        elif mag.name in devices:
            devices[mag.name]["rate_hz"] = mag.rate_hz
    nominal = [[float(v) for v in row] for row in cfg.cage.coil_matrix_ut_per_a]
    return rig_config_toml({"devices": devices}, cfg.source, nominal)


def run_sim(
    config_path: str | None,
    endpoints_json: Path | None,
    rig_config: Path | None,
    duration_s: float | None,
    quiet: bool,
) -> int:
    """Start the cage, publish its endpoints, wait for a stop request, stop cleanly."""
    from sim.cage import SimulatedCage
    from sim.config import DEFAULT_CONFIG, SimConfigError, load_config

    try:
        cfg = load_config(config_path or DEFAULT_CONFIG)
    except SimConfigError as exc:
        raise UserInputError(f"{exc}: fix the file or omit --config for the default cage") from None
    stop = threading.Event()
    received: list[int] = []

    def on_signal(signum: int, frame: FrameType | None) -> None:
        received.append(signum)
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    cage = SimulatedCage(cfg)
    try:
        endpoints = cage.start()
        text = json.dumps(endpoints, indent=2) + "\n"
        for path, content in (
            (endpoints_json, text),
            (rig_config, sim_rig_config(endpoints, cfg)),
        ):
            if path is not None:
                try:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_suffix(path.suffix + ".tmp")
                    tmp.write_text(content, encoding="utf-8")
                    tmp.replace(path)  # readers never see a half-written file
                except OSError as exc:
                    raise UserInputError(f"cannot write {path}: {exc.strerror}") from None
        if not quiet:
            print(f"simulated cage running ({cfg.source}); loopback only. Devices:")
            for name, dev in endpoints["devices"].items():
                where = dev.get("path") or f"{dev.get('host', '')}:{dev.get('port', '')}"
                if dev.get("protocol") == "i2c":
                    where = f"in-process bus, address 0x{dev['address']:02x}"
                print(f"  {name:<12} {dev['kind']:<14} {dev['protocol']:<11} {where}")
            for path in (endpoints_json, rig_config):
                if path is not None:
                    print(f"wrote {path}")
            print("press Ctrl-C to stop", flush=True)
        deadline = None if duration_s is None else time.monotonic() + duration_s
        while not stop.wait(0.2):
            if deadline is not None and time.monotonic() >= deadline:
                break
    finally:
        cage.stop()
        for s, handler in old.items():
            signal.signal(s, handler)
    if not quiet:
        print("simulated cage stopped; all outputs off", flush=True)
    return 0
