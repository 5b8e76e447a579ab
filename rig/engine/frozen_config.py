"""The rig configuration as the rig process parsed it, frozen into one line of JSON for the guardian.

The guardian must switch off exactly the devices the rig opened, whatever happens to the
configuration file meanwhile (an edit that breaks its syntax or renames a device): the session
hands it this copy on its pipe when it starts, and the guardian never reads the file.
Only what acting needs is carried: the devices and the cage section (not ``raw``: a ``[lab] url``
with a password has no business in another process).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from rig.config import CageConfig, DeviceConfig, RigConfig


class FrozenConfigError(ValueError):
    """The frozen copy cannot be read back (not the JSON :func:`freeze` writes)."""


def freeze(cfg: RigConfig) -> str:
    """``cfg``'s devices and cage as one line of JSON (no line break inside)."""
    c = cfg.cage
    cage: dict[str, Any] | None = None
    if c is not None:
        cage = {
            "axes": list(c.axes),
            "polarity": c.polarity,
            "reference": c.reference,
            "calibration": None if c.calibration is None else str(c.calibration),
            "max_current_a": list(c.max_current_a),
            "max_field_ut": c.max_field_ut,
            "max_slew_a_per_s": c.max_slew_a_per_s,
            "compliance_v": c.compliance_v,
            "step_s": c.step_s,
            "nominal_k_ut_per_a": None
            if c.nominal_k_ut_per_a is None
            else [list(r) for r in c.nominal_k_ut_per_a],
            "calibration_valid_days": c.calibration_valid_days,
            "ambient": c.ambient,
            "scalar": c.scalar,
            "ambient_gradient_nt_per_m": c.ambient_gradient_nt_per_m,
            "max_ambient_ut": c.max_ambient_ut,
            "coil_tau_s": c.coil_tau_s,
            "trim": None if c.trim is None else list(c.trim),
            "trim_ut_per_a": None if c.trim_ut_per_a is None else list(c.trim_ut_per_a),
        }
    devices = {
        n: {"kind": d.kind, "protocol": d.protocol, "params": d.params}
        for n, d in cfg.devices.items()
    }
    doc = {"path": str(cfg.path), "devices": devices, "cage": cage}
    return json.dumps(doc, default=str, separators=(",", ":"))


def thaw(text: str) -> RigConfig:
    """The :class:`RigConfig` :func:`freeze` wrote (``raw`` empty); FrozenConfigError if ``text``
    is anything else."""
    try:
        doc = json.loads(text)
        devices = {
            str(n): DeviceConfig(str(n), str(d["kind"]), str(d["protocol"]), dict(d["params"]))
            for n, d in doc["devices"].items()
        }
        c = doc["cage"]
        cage = None
        if c is not None:
            nominal = c["nominal_k_ut_per_a"]
            cage = CageConfig(
                axes=(str(c["axes"][0]), str(c["axes"][1]), str(c["axes"][2])),
                polarity=c["polarity"],
                reference=c["reference"],
                calibration=None if c["calibration"] is None else Path(c["calibration"]),
                max_current_a=(
                    float(c["max_current_a"][0]),
                    float(c["max_current_a"][1]),
                    float(c["max_current_a"][2]),
                ),
                max_field_ut=float(c["max_field_ut"]),
                max_slew_a_per_s=float(c["max_slew_a_per_s"]),
                compliance_v=float(c["compliance_v"]),
                step_s=float(c["step_s"]),
                nominal_k_ut_per_a=None
                if nominal is None
                else tuple(tuple(float(v) for v in row) for row in nominal),
                calibration_valid_days=float(c.get("calibration_valid_days", 90.0)),
                ambient=c.get("ambient"),
                scalar=c.get("scalar"),
                ambient_gradient_nt_per_m=float(c.get("ambient_gradient_nt_per_m", 15.0)),
                max_ambient_ut=float(c.get("max_ambient_ut", 66.0)),
                coil_tau_s=None if c.get("coil_tau_s") is None else float(c["coil_tau_s"]),
                trim=None if c.get("trim") is None else (c["trim"][0], c["trim"][1], c["trim"][2]),
                trim_ut_per_a=None
                if c.get("trim_ut_per_a") is None
                else (
                    float(c["trim_ut_per_a"][0]),
                    float(c["trim_ut_per_a"][1]),
                    float(c["trim_ut_per_a"][2]),
                ),
            )
        return RigConfig(Path(doc["path"]), devices, cage, {})
    except (ValueError, KeyError, TypeError, IndexError, AttributeError) as exc:
        raise FrozenConfigError(
            f"not a frozen rig configuration ({type(exc).__name__}: {exc})"
        ) from exc
