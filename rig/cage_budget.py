"""The cage's terms of a DUT calibration's uncertainty budget, as errors of the reference field
(:class:`rig.calibration.budget.FieldTerm`, ADR 0028):

- the reference's certificate: each scale factor, each axis angle of its lower-triangular sensor
  matrix and its mounting about each cage axis, at the certificate's 1-sigma;
- the cage's homogeneity between the reference's place and the DUT's (the field map of the cage
  calibration record): applied as a correction, its uncertainty as terms along the principal
  directions of each coil map's covariance;
- the lab field's difference between the two places: its gradient's 1-sigma (Type B, the rig
  configuration) times the distance.

The coil constants and axes are not terms of their own: the reference measures the field the
coils make, so they enter only through the homogeneity correction (``dK K^-1``), a second-order
effect there.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from rig.cage.coil_axes import ARCSEC_PER_RAD, lower_triangular_part, rotation
from rig.calibration.budget import CageTerms, FieldTerm
from rig.config import RigConfig

Array = npt.NDArray[np.float64]
AXES = ("x", "y", "z")
CERTIFICATE = "reference certificate"
HOMOGENEITY = "cage homogeneity (field map)"
LAB_FIELD = "lab field between reference and DUT"


@dataclass(frozen=True)
class Certificate:
    """The reference's certificate: ``correction_matrix`` (raw to cage frame) and its 1-sigma:
    ``scale_sigma`` (relative), ``angle_sigma_arcsec`` (axis angles), ``mounting_sigma_arcsec``
    (rotation about each cage axis)."""

    correction_matrix: Array
    scale_sigma: float
    angle_sigma_arcsec: float
    mounting_sigma_arcsec: float

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> Certificate | None:
        """From the reference's rig-configuration keys (or a run's recorded copy); None without a
        correction matrix."""
        if params.get("correction_matrix") is None and params.get("matrix") is None:
            return None
        matrix = params.get("correction_matrix", params.get("matrix"))
        return cls(np.array(matrix, float).reshape(3, 3),
                   float(params.get("correction_scale_sigma", 5e-5)),
                   float(params.get("correction_angle_sigma_arcsec", 20.0)),
                   float(params.get("correction_mounting_sigma_arcsec", 30.0)))  # fmt: skip


def _term(name: str, group: str, t_cert: Array, t_moved: Array) -> FieldTerm:
    """The field error when the true sensor matrix is ``t_moved`` while the certificate says
    ``t_cert``: ``h_true = t_moved^-1 t_cert h``."""
    return FieldTerm(name, group, np.linalg.solve(t_moved, t_cert) - np.eye(3))


def certificate_terms(cert: Certificate) -> list[FieldTerm]:
    """Nine terms: scale of each sensor axis, the three angles between its axes, its mounting
    about each cage axis, each at its 1-sigma."""
    t = np.asarray(np.linalg.inv(cert.correction_matrix), float)
    lower = lower_triangular_part(t)
    mount = np.linalg.solve(lower, t)
    angle = cert.angle_sigma_arcsec / ARCSEC_PER_RAD
    out = []
    for i, ax in enumerate(AXES):
        scale = np.eye(3)
        scale[i, i] += cert.scale_sigma
        out.append(_term(f"scale {ax}", CERTIFICATE, t, scale @ t))
    for i, j in ((1, 0), (2, 0), (2, 1)):
        moved = lower.copy()
        moved[i, j] += angle * lower[i, i]
        out.append(_term(f"angle {AXES[j]}{AXES[i]}", CERTIFICATE, t, moved @ mount))
    for i, ax in enumerate(AXES):
        turn = np.zeros(3)
        turn[i] = cert.mounting_sigma_arcsec / ARCSEC_PER_RAD
        out.append(_term(f"mounting about {ax}", CERTIFICATE, t, t @ rotation(turn)))
    return out


def homogeneity_terms(
    maps: Sequence[Mapping[str, Any]],
    reference_m: Array,
    dut_m: Array,
    k_ut_per_a: Array,
    b0_ut: Array,
) -> tuple[FieldTerm, list[FieldTerm]]:
    """The correction from the reference's place to the DUT's and its terms, from the field maps
    of the three coils (``maps``: degree, coefficients, covariance of
    :class:`rig.cage.homogeneity.FieldMap`, uT/A): ``h_dut = h_ref + dK I`` with the coil
    currents ``I = K^-1 (h_ref - B0)``, ``dK`` the map's field per ampere at the DUT less at the
    reference (uT/A)."""
    from rig.cage.homogeneity import field_basis

    k_inv = np.linalg.inv(np.asarray(k_ut_per_a, float))
    b0 = np.asarray(b0_ut, float)
    d_k = np.zeros((3, 3))
    covs = []
    for coil, m in enumerate(maps):
        degree = int(m["degree"])
        a = field_basis(np.vstack([dut_m, reference_m]), degree)
        diff = a[0] - a[1]  # (3, P)
        d_k[:, coil] = diff @ np.asarray(m["coefficients"], float)
        covs.append(diff @ np.asarray(m["covariance"], float) @ diff.T)

    def term(name: str, dk: Array) -> FieldTerm:
        g = dk @ k_inv
        return FieldTerm(name, HOMOGENEITY, g, -g @ b0)

    correction = term("correction", d_k)
    terms = []
    for coil, cov in enumerate(covs):
        values, vectors = np.linalg.eigh(cov)
        for n, (lam, vec) in enumerate(zip(values, vectors.T, strict=True)):
            dk = np.zeros((3, 3))
            dk[:, coil] = math.sqrt(max(float(lam), 0.0)) * vec
            terms.append(term(f"coil {AXES[coil]} map, direction {n + 1}", dk))
    return correction, terms


def lab_field_terms(
    gradient_sigma_nt_per_m: float, reference_m: Array, dut_m: Array
) -> list[FieldTerm]:
    """The lab field's difference between the two places: per axis, the gradient's 1-sigma times
    their distance (an offset of the field, uT)."""
    distance = float(np.linalg.norm(np.asarray(dut_m, float) - np.asarray(reference_m, float)))
    if distance == 0.0 or gradient_sigma_nt_per_m == 0.0:
        return []
    out = []
    for i, ax in enumerate(AXES):
        offset = np.zeros(3)
        offset[i] = gradient_sigma_nt_per_m * distance / 1000.0
        out.append(FieldTerm(f"{ax}", LAB_FIELD, offset_ut=offset))
    return out


DUT_M = np.zeros(3)
"""The DUT's place: the cage centre (the origin of the cage frame and of the field map)."""


def cage_terms(
    reference: Mapping[str, Any] | None,
    cage_model: Mapping[str, Any] | None,
    gradient_sigma_nt_per_m: float,
) -> CageTerms:
    """The cage's terms of a run: ``reference`` the reference's certificate as the run recorded it
    (``matrix`` or ``correction_matrix``, the sigma keys, ``position_m``), ``cage_model`` the cage
    calibration record in use (``k_ut_per_a``, ``b0_ut``, ``metrology.field_map.maps``)."""
    cert = Certificate.from_params(reference or {})
    if cert is None:
        return CageTerms(
            left_out=("the reference's certificate: the run has no correction_matrix",)
        )
    terms = certificate_terms(cert)
    left_out = []
    where = (reference or {}).get("position_m")
    ref_m = np.zeros(3) if where is None else np.array(where, float).reshape(3)
    if where is None:
        left_out.append(
            "the reference's place: give its position_m in the rig configuration"
            " (taken as the DUT's, so no homogeneity or lab-field term)"
        )
    model = cage_model or {}
    maps = (model.get("metrology") or {}).get("field_map", {}).get("maps")
    correction = None
    if maps and np.any(ref_m != DUT_M):
        k = np.asarray(model["k_ut_per_a"], float)
        correction, more = homogeneity_terms(
            maps, ref_m, DUT_M, k, np.asarray(model["b0_ut"], float)
        )
        terms += more
    elif np.any(ref_m != DUT_M):
        left_out.append(
            "the cage's homogeneity between the reference and the DUT: no field map"
            " in the cage calibration record (rig run cage-field-map)"
        )
    terms += lab_field_terms(gradient_sigma_nt_per_m, ref_m, DUT_M)
    return CageTerms(correction, tuple(terms), tuple(left_out))


CERTIFICATE_KEYS = ("correction_scale_sigma", "correction_angle_sigma_arcsec",
                    "correction_mounting_sigma_arcsec", "position_m")  # fmt: skip
"""The reference's keys the run records beside its correction (the uncertainty budget's)."""


def certificate_of(cfg: RigConfig, reference: str | None) -> dict[str, Any] | None:
    """Device ``reference``'s certificate (matrix and offset, with their 1-sigma) and its place in
    the cage (``position_m``, when given) as a run records them; None without one."""
    if not reference or reference not in cfg.devices:
        return None
    dev = cfg.devices[reference]
    if dev.get("correction_matrix") is None:
        return None
    return {
        "matrix": dev.get("correction_matrix"),
        "offset_ut": dev.get("correction_offset_ut", [0, 0, 0]),
        **{k: dev.get(k) for k in CERTIFICATE_KEYS if dev.get(k) is not None},
    }


def run_cage_terms(meta: Mapping[str, Any], rig_toml_text: str | None) -> CageTerms:
    """The cage's terms of a recorded run, for a refit of it (``rig calibrate RUN``): the
    reference's certificate and the cage record the run recorded (``reference_correction``,
    ``cage_model``) and the lab gradient's 1-sigma of the run's copy of its rig configuration."""
    import tomllib

    gradient = 15.0
    if rig_toml_text is not None:
        try:
            cage = tomllib.loads(rig_toml_text).get("cage", {})
            gradient = float(cage.get("ambient_gradient_nt_per_m", gradient))
        except (tomllib.TOMLDecodeError, TypeError, ValueError):
            pass  # the run's copy was checked when the run started; the default then
    return cage_terms(meta.get("reference_correction"), meta.get("cage_model"), gradient)
