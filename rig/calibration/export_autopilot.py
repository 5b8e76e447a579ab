"""Export a calibration as autopilot parameters: ArduPilot ``.parm`` and PX4 ``.params`` (text only).

Our correction (uT) is ``h = W (m - o - sum_j k_j u_j)``. Both autopilots take a symmetric soft-iron
matrix, so ``W`` is split by its polar decomposition ``W = R S`` (``R`` a rotation, ``S`` symmetric
positive definite; ``S`` is ``I + D`` of the result's Crassidis block). ``S`` is exported and ``R``
is left out: the autopilot's output is ``R^T h``, the same magnitude and, up to that fixed rotation,
the same direction. For a vector fit ``R`` is the mounting/frame rotation the data show, which the
autopilot's orientation parameter handles; for a scalar fit it is the arbitrary frame of the
triangular ``W`` (the mounting is unobservable), and the file says not to set orientation from it.

ArduPilot, as applied in ``AP_Compass_Backend::correct_field`` (field in mGauss)::

    corrected = M * COMPASS_SCALE * (raw + COMPASS_OFS) + COMPASS_MOT * current_A
    M = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]

``raw`` is the field after ``COMPASS_ORIENT``/``AHRS_ORIENTATION`` (body axes); compass 2 and 3 use
``COMPASS_OFS2_X``, ``COMPASS_DIA2_X``, ``COMPASS_SCALE2``, ``COMPASS_MOT2_X`` and so on. Export:
``M = S``, ``OFS = -10 o`` (mGauss), ``SCALE = 1``, ``MOT = -10 S k`` (mGauss/A, one channel: the
battery current with ``COMPASS_MOTCT = 2``). Refused outside the calibrator's accepted fit
(``0.2 < DIA < 5``, ``|ODI| < 1``), an offset longer than 3000 mGauss (the top of
``COMPASS_OFFS_MAX``) or ``|MOT|`` above its documented 1000 mGauss/A.

PX4, as applied in ``calibration::Magnetometer::Correct`` (field in gauss)::

    corrected = ROT * S * (raw + CAL_MAGn_COMP * current_kA - CAL_MAGn_OFF)
    S = [[XSCALE, XODIAG, YODIAG], [XODIAG, YSCALE, ZODIAG], [YODIAG, ZODIAG, ZSCALE]]

``raw`` is the driver's ``sensor_mag`` frame, before ``CAL_MAGn_ROT``/the board rotation ``ROT``.
Export: ``S``, ``OFF = 0.01 o`` (gauss), ``COMP = -10 k`` (gauss/kA, one channel: battery current
with ``CAL_MAG_COMP_TYP = 2``). Refused outside the documented ``0.1 <= SCALE <= 3``.

Sources read to verify these conventions (no code taken from them):
ArduPilot/ardupilot ``libraries/AP_Compass/AP_Compass_Backend.cpp`` (correct_field, rotate_field),
``libraries/AP_Compass/AP_Compass.cpp`` (parameter names, units, ranges),
``libraries/AP_Compass/AP_Compass_Calibration.cpp`` (what a calibration saves),
``libraries/AP_Compass/CompassCalibrator.cpp`` (fit_acceptable); ArduPilot/pymavlink ``mavparm.py``
(``.parm`` loading: ``#`` comments, ``NAME,VALUE``); PX4/PX4-Autopilot
``src/lib/sensor_calibration/Magnetometer.hpp`` and ``Magnetometer.cpp`` (Correct, set_scale,
set_offdiagonal), ``src/modules/sensors/module.yaml`` and ``sensor_params_mag.yaml`` (parameters),
``src/modules/sensors/vehicle_magnetometer/VehicleMagnetometer.cpp`` (current in kA);
mavlink/qgroundcontrol ``docs/en/qgc-dev-guide/file_formats/parameters.md`` (``.params`` format).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.calibration.params import Array, crassidis_from_correction
from rig.calibration.result import CalibrationResult

MGAUSS_PER_UT = 10.0
"""1 G = 100 uT, so 1 uT = 10 mGauss."""
GAUSS_PER_UT = 0.01
ARDUPILOT_COMPASSES = (1, 2, 3)
ARDUPILOT_DIA_RANGE = (0.2, 5.0)
"""Open interval CompassCalibrator.cpp ``fit_acceptable`` accepts for DIA_X/Y/Z."""
ARDUPILOT_ODI_MAX = 1.0
"""``|ODI_X/Y/Z|`` must stay below this (``fit_acceptable``)."""
ARDUPILOT_OFFS_MAX_DEFAULT_MGAUSS = 1800.0
ARDUPILOT_OFFS_MAX_TOP_MGAUSS = 3000.0
"""COMPASS_OFFS_MAX: default and top of its documented range (the arming check on ``|OFS|``)."""
ARDUPILOT_MOT_MAX_MGAUSS_PER_A = 1000.0
PX4_INSTANCES = range(4)
PX4_SCALE_RANGE = (0.1, 3.0)
"""Documented min/max of CAL_MAGn_XSCALE/YSCALE/ZSCALE (module.yaml)."""
MAV_PARAM_TYPE_REAL32 = 9
MAV_PARAM_TYPE_INT32 = 6
AXES = ("X", "Y", "Z")


@dataclass(frozen=True)
class _Split:
    """The correction as the autopilots can take it: ``W = R S``, offset, one current channel."""

    s: Array
    r: Array
    offset_ut: Array
    channel: str | None
    k_ut_per_a: Array | None
    left_out: tuple[str, ...]

    @property
    def diagonal(self) -> Array:
        """S_xx, S_yy, S_zz (ArduPilot DIA, PX4 SCALE)."""
        return np.diag(self.s).copy()

    @property
    def off_diagonal(self) -> Array:
        """S_xy, S_xz, S_yz, in the order both autopilots name them (ODI_X/Y/Z, X/Y/ZODIAG)."""
        return np.array([self.s[0, 1], self.s[0, 2], self.s[1, 2]])


def _split(result: CalibrationResult, who: str, current_channel: str | None) -> _Split:
    cal = result.calibration
    w = np.asarray(cal.correction_matrix, dtype=float)
    values = np.concatenate([w.ravel(), cal.offset_ut, cal.k_ut_per_unit.ravel()])
    if not np.all(np.isfinite(values)):
        raise ValueError(f"cannot export to {who}: the calibration has non-finite values")
    if not np.linalg.det(w) > 0:
        raise ValueError(
            f"cannot export to {who}: the correction inverts an axis (det W <= 0), which no"
            " rotation can represent: check the axis order and signs of the readings"
        )
    cr, r = crassidis_from_correction(w, cal.offset_ut)
    s = np.eye(3) + cr.d_matrix
    if current_channel is not None and current_channel not in cal.channels:
        known = ", ".join(cal.channels) or "none"
        raise ValueError(
            f"cannot export to {who}: no telemetry channel '{current_channel}' in this"
            f" calibration (its channels: {known})"
        )
    k = None
    if current_channel is not None:
        k = np.asarray(cal.k_ut_per_unit[cal.channels.index(current_channel)], dtype=float)
    left_out = tuple(ch for ch in cal.channels if ch != current_channel)
    return _Split(s, np.asarray(r), np.asarray(cal.offset_ut, float), current_channel, k, left_out)


def _num(value: float) -> str:
    """A parameter value: 9 significant digits (float32 round trip), never ``-0``."""
    text = f"{float(value):.9g}"
    return "0" if text in ("-0", "0") else text


def _rotation_comment(split: _Split, orientation: str, model: str) -> str:
    """The left-out rotation: for a vector fit the mounting the data show; for a scalar fit an
    arbitrary by-product of the triangular ``W`` (the mounting is unobservable), never a mounting."""
    from scipy.spatial.transform import Rotation

    rotvec = Rotation.from_matrix(split.r).as_rotvec()
    angle = math.degrees(float(np.linalg.norm(rotvec)))
    axis = rotvec / np.linalg.norm(rotvec) if angle > 0 else np.array([1.0, 0.0, 0.0])
    about = ", ".join(f"{a:+.4f}" for a in axis)
    if model == "scalar":
        return (
            f"# left out: rotation R of W = R S, {angle:.3f} deg about ({about}): the arbitrary"
            " frame of a scalar (attitude-independent) fit, not the mounting: do not set"
            f" {orientation.split()[0]} from it"
        )
    return (
        f"# left out: rotation R of W = R S, {angle:.3f} deg about ({about}): a mounting/frame"
        f" rotation, set with {orientation} if it matters"
    )


def _header(result: CalibrationResult, autopilot: str, source: str) -> list[str]:
    return [
        f"# {autopilot} magnetometer calibration generated by rig ({result.model} model,"
        f" method {result.method})",
        f"# source: {source or 'in-memory data'}; {result.samples} samples; residual rms"
        f" {result.residual_rms_nt:.1f} nT",
        "# rig's correction (uT): h = W (m - o - sum_j k_j u_j); exported: S of W = R S"
        " (symmetric), o, and one current channel's k if named",
    ]


def _left_out_channels(split: _Split, where: str, result: CalibrationResult) -> list[str]:
    lines = [f"# {line}" for line in result.unexported_model(where)]
    if not split.left_out:
        return lines
    names = ", ".join(split.left_out)
    return [
        f"# left out: current-to-bias of channel(s) {names}: {where} takes one current channel"
        " (name it to export it)",
        *lines,
    ]


def _ardupilot_values(split: _Split, who: str) -> tuple[Array, Array, Array, Array | None]:
    """(OFS mGauss, DIA, ODI, MOT mGauss/A or None) of ``split``; ValueError (one line) when a
    value is outside what ArduPilot accepts."""
    s = split.s
    dia, odi = split.diagonal, split.off_diagonal
    lo, hi = ARDUPILOT_DIA_RANGE
    if np.any(dia <= lo) or np.any(dia >= hi):
        raise ValueError(
            f"cannot export to {who}: DIA {_triple(dia)} outside ({lo:g}, {hi:g}), the range"
            " ArduPilot's calibrator accepts"
        )
    if np.any(np.abs(odi) >= ARDUPILOT_ODI_MAX):
        raise ValueError(
            f"cannot export to {who}: ODI {_triple(odi)} not within +-{ARDUPILOT_ODI_MAX:g},"
            " the range ArduPilot's calibrator accepts"
        )
    ofs = -MGAUSS_PER_UT * split.offset_ut
    ofs_len = float(np.linalg.norm(ofs))
    if ofs_len > ARDUPILOT_OFFS_MAX_TOP_MGAUSS:
        raise ValueError(
            f"cannot export to {who}: offset length {ofs_len:.0f} mGauss exceeds"
            f" {ARDUPILOT_OFFS_MAX_TOP_MGAUSS:.0f}, the most COMPASS_OFFS_MAX allows"
        )
    mot = None
    if split.k_ut_per_a is not None:
        mot = -MGAUSS_PER_UT * (s @ split.k_ut_per_a)
        if np.any(np.abs(mot) > ARDUPILOT_MOT_MAX_MGAUSS_PER_A):
            raise ValueError(
                f"cannot export to {who}: COMPASS_MOT {_triple(mot)} mGauss/A outside"
                f" +-{ARDUPILOT_MOT_MAX_MGAUSS_PER_A:.0f}, its documented range"
            )
    return ofs, dia, odi, mot


def ardupilot_params(
    result: CalibrationResult,
    compass: int = 1,
    *,
    current_channel: str | None = None,
    source: str = "",
) -> str:
    """An ArduPilot parameter file (``NAME,VALUE`` lines, Mission Planner/MAVProxy ``.parm``).

    Offsets in mGauss (``COMPASS_OFS* = -10 o``, ArduPilot adds them), the symmetric soft-iron
    ``COMPASS_DIA*``/``COMPASS_ODI*``, ``COMPASS_SCALE* = 1``; with ``current_channel`` (a
    telemetry channel in A) also ``COMPASS_MOTCT = 2`` and ``COMPASS_MOT*`` in mGauss/A.
    ``compass`` is 1, 2 or 3. Raises ValueError (one line) when the result cannot be exported.
    """
    who = f"ArduPilot compass {compass}"
    if compass not in ARDUPILOT_COMPASSES:
        raise ValueError(f"ArduPilot compass must be 1, 2 or 3, got {compass}")
    split = _split(result, who, current_channel)
    ofs, dia, odi, mot = _ardupilot_values(split, who)
    ofs_len = float(np.linalg.norm(ofs))
    n = "" if compass == 1 else str(compass)
    lines = _header(result, f"ArduPilot (compass {compass})", source)
    lines += [
        "# applied as (mGauss): corrected = M * SCALE * (raw + OFS) + MOT * current,"
        " M = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]",
        "# axes: raw is the field after COMPASS_ORIENT/AHRS_ORIENTATION (vehicle body axes),"
        " the axes of the calibration data; OFS = -10 * o (ArduPilot adds offsets)",
        f"# compass {compass} is the slot whose COMPASS_DEV_ID{n} is this magnetometer",
        _rotation_comment(split, f"COMPASS_ORIENT{n} (custom rotation)", result.model),
    ]
    if ofs_len > ARDUPILOT_OFFS_MAX_DEFAULT_MGAUSS:
        lines.append(
            f"# note: offset length {ofs_len:.0f} mGauss exceeds the default COMPASS_OFFS_MAX"
            f" {ARDUPILOT_OFFS_MAX_DEFAULT_MGAUSS:.0f}: raise it to arm"
        )
    if mot is not None:
        lines.append(
            f"# current: channel '{split.channel}' must be the battery monitor's current in A;"
            f" MOT = -10 * S k (added after the matrix)"
        )
    lines += _left_out_channels(split, "ArduPilot", result)
    groups = [("OFS", ofs), ("DIA", dia), ("ODI", odi)]
    if mot is not None:
        groups.append(("MOT", mot))
    params = [
        (f"COMPASS_{group}{n}_{a}", float(v))
        for group, values in groups
        for a, v in zip(AXES, values, strict=True)
    ]
    params.append((f"COMPASS_SCALE{n}", 1.0))
    if mot is not None:
        params.append(("COMPASS_MOTCT", 2.0))
    lines += [f"{name},{_num(value)}" for name, value in params]
    return "\n".join(lines) + "\n"


def px4_params(
    result: CalibrationResult,
    instance: int = 0,
    *,
    current_channel: str | None = None,
    source: str = "",
) -> str:
    """A PX4 parameter set in QGroundControl's ``.params`` format (tab-separated).

    ``CAL_MAGn_XOFF/YOFF/ZOFF`` in gauss (``0.01 o``, PX4 subtracts them) and the symmetric
    ``CAL_MAGn_XSCALE...``/``CAL_MAGn_XODIAG...``; with ``current_channel`` (a telemetry channel
    in A) also ``CAL_MAG_COMP_TYP = 2`` and ``CAL_MAGn_XCOMP...`` in gauss/kA. ``instance`` is
    0 to 3. Raises ValueError (one line) when the result cannot be exported.
    """
    who = f"PX4 CAL_MAG{instance}"
    if instance not in PX4_INSTANCES:
        raise ValueError(f"PX4 magnetometer instance must be 0 to 3, got {instance}")
    split = _split(result, who, current_channel)
    scale, odiag = split.diagonal, split.off_diagonal
    lo, hi = PX4_SCALE_RANGE
    if np.any(scale < lo) or np.any(scale > hi):
        raise ValueError(
            f"cannot export to {who}: SCALE {_triple(scale)} outside [{lo:g}, {hi:g}], the"
            " documented range"
        )
    off = GAUSS_PER_UT * split.offset_ut
    comp = None
    if split.k_ut_per_a is not None:
        comp = -GAUSS_PER_UT * 1000.0 * split.k_ut_per_a
    p = f"CAL_MAG{instance}_"
    lines = _header(result, f"PX4 ({p}*)", source)
    lines += [
        "# applied as (gauss): corrected = ROT * S * (raw + COMP * current_kA - OFF),"
        " S = [[XSCALE, XODIAG, YODIAG], [XODIAG, YSCALE, ZODIAG], [YODIAG, ZODIAG, ZSCALE]]",
        "# axes: raw is the driver's sensor_mag frame (before CAL_MAGn_ROT and the board"
        " rotation), the axes of the calibration data; OFF = 0.01 * o (PX4 subtracts offsets)",
        f"# instance {instance} is the slot whose {p}ID is this magnetometer (not written here)",
        _rotation_comment(
            split, f"{p}ROT (custom Euler angles, external magnetometers)", result.model
        ),
    ]
    if comp is not None:
        lines.append(
            f"# current: channel '{split.channel}' must be battery_status instance 0's current"
            " in A; COMP = -10 * k gauss/kA (added before the offset, in the sensor frame)"
        )
    lines += _left_out_channels(split, "PX4", result)
    groups = [("OFF", off), ("SCALE", scale), ("ODIAG", odiag)]
    params: list[tuple[str, float, int]] = []
    if comp is not None:
        groups.append(("COMP", comp))
        params.append(("CAL_MAG_COMP_TYP", 2.0, MAV_PARAM_TYPE_INT32))
    for group, values in groups:
        params += [
            (f"{p}{a}{group}", float(v), MAV_PARAM_TYPE_REAL32)
            for a, v in zip(AXES, values, strict=True)
        ]
    lines += ["#", "# Vehicle-Id Component-Id Name Value Type"]
    lines += [f"1\t1\t{name}\t{_num(value)}\t{kind}" for name, value, kind in params]
    return "\n".join(lines) + "\n"


def _triple(v: Array) -> str:
    return "(" + ", ".join(f"{float(x):.4g}" for x in v) + ")"
