"""Autopilot parameter exports (rig/calibration/export_autopilot.py) against the autopilots' own
correction formulas, written here from their documented definitions, not taken from the module:

* ArduPilot (AP_Compass_Backend.cpp correct_field), mGauss, offsets ADDED, motor term after the
  matrix: ``corrected = M * SCALE * (raw + OFS) + MOT * current_A``
* PX4 (sensor_calibration/Magnetometer.hpp Correct), gauss, offsets SUBTRACTED, current in kA:
  ``corrected = S * (raw + COMP * current_kA - OFF)``

Both matrices are symmetric ``[[X, XY, XZ], [XY, Y, YZ], [XZ, YZ, Z]]`` with the off-diagonals
named X (xy), Y (xz), Z (yz). The export leaves out the rotation ``R`` of ``W = R S``, so the
autopilot's field equals ours in magnitude and, after ``R``, in direction."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rig.calibration import Calibration, CalibrationResult, calibrate
from rig.calibration.export_autopilot import ardupilot_params, px4_params
from rig.calibration.synthetic import SyntheticCase
from rig.cli import main

SPHERE = Path(__file__).resolve().parent / "data" / "real-magnetometer" / "space-denpa-set1.csv"
REAL_ARGS = ["--measured", "x,y,z", "--unit", "G", "--field-magnitude", "0.47"]
XYZ = ("X", "Y", "Z")


# --- the autopilots' side, written from their definitions -------------------------------------


def parse_parm(text: str) -> dict[str, float]:
    """Mission Planner/MAVProxy: ``#`` comment lines, ``NAME,VALUE`` lines."""
    out: dict[str, float] = {}
    for line in text.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        name, value = line.split(",")
        out[name.strip()] = float(value)
    return out


def parse_qgc(text: str) -> dict[str, float]:
    """QGroundControl: ``#`` comments, ``vehicle component name value type`` tab-separated."""
    out: dict[str, float] = {}
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        vehicle, component, name, value, kind = line.split("\t")
        assert (vehicle, component) == ("1", "1")
        assert kind == ("6" if name == "CAL_MAG_COMP_TYP" else "9")  # INT32, REAL32
        out[name] = float(value)
    return out


def symmetric(diag: list[float], off: list[float]) -> np.ndarray:
    (dx, dy, dz), (ox, oy, oz) = diag, off
    return np.array([[dx, ox, oy], [ox, dy, oz], [oy, oz, dz]])


def ardupilot_field_ut(p: dict[str, float], raw_ut: np.ndarray, amps: np.ndarray | None,
                       compass: int = 1) -> np.ndarray:  # fmt: skip
    n = "" if compass == 1 else str(compass)
    raw_mgauss = 10.0 * raw_ut  # 1 uT = 10 mGauss
    ofs = np.array([p[f"COMPASS_OFS{n}_{a}"] for a in XYZ])
    m = symmetric([p[f"COMPASS_DIA{n}_{a}"] for a in XYZ], [p[f"COMPASS_ODI{n}_{a}"] for a in XYZ])
    scale = p.get(f"COMPASS_SCALE{n}", 0.0) or 1.0  # 0 means no scaling
    out = (scale * (raw_mgauss + ofs)) @ m.T
    if amps is not None and p.get("COMPASS_MOTCT") == 2:
        out = out + np.outer(amps, [p[f"COMPASS_MOT{n}_{a}"] for a in XYZ])
    return np.asarray(out / 10.0)


def px4_field_ut(p: dict[str, float], raw_ut: np.ndarray, amps: np.ndarray | None,
                 instance: int = 0) -> np.ndarray:  # fmt: skip
    c = f"CAL_MAG{instance}_"
    raw_gauss = 0.01 * raw_ut  # 1 G = 100 uT
    off = np.array([p[f"{c}{a}OFF"] for a in XYZ])
    s = symmetric([p[f"{c}{a}SCALE"] for a in XYZ], [p[f"{c}{a}ODIAG"] for a in XYZ])
    v = raw_gauss - off
    if amps is not None and p.get("CAL_MAG_COMP_TYP") == 2:
        v = v + np.outer(amps / 1000.0, [p[f"{c}{a}COMP"] for a in XYZ])  # current in kA
    return np.asarray((v @ s.T) / 0.01)


def soft_iron(p: dict[str, float], autopilot: str) -> np.ndarray:
    if autopilot == "ardupilot":
        return symmetric([p[f"COMPASS_DIA_{a}"] for a in XYZ], [p[f"COMPASS_ODI_{a}"] for a in XYZ])
    return symmetric([p[f"CAL_MAG0_{a}SCALE"] for a in XYZ], [p[f"CAL_MAG0_{a}ODIAG"] for a in XYZ])


def assert_equal_up_to_rotation(got: np.ndarray, want: np.ndarray, w: np.ndarray,
                                s: np.ndarray) -> np.ndarray:  # fmt: skip
    """|got| = |want| to 1e-6 relative, and ``R got = want`` with ``R = W S^-1`` a rotation."""
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), np.linalg.norm(want, axis=1),
                               rtol=1e-6)  # fmt: skip
    r = w @ np.linalg.inv(s)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-7)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-7)
    scale = np.linalg.norm(want, axis=1)[:, None]
    np.testing.assert_allclose(got @ r.T / scale, want / scale, atol=1e-6)
    return r


def left_out_angle_deg(text: str) -> float:
    match = re.search(r"rotation R of W = R S, ([0-9.]+) deg", text)
    assert match, text
    return float(match.group(1))


def rotation_angle_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


# --- round trips --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cage_result(cage_case: SyntheticCase) -> CalibrationResult:
    """Vector fit of the cage sweep: mounting rotation, two load channels."""
    return calibrate(cage_case.samples)


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_cage_round_trip_with_one_current_channel(
    cage_case: SyntheticCase, cage_result: CalibrationResult, autopilot: str
) -> None:
    cal = cage_result.calibration
    if autopilot == "ardupilot":
        text = ardupilot_params(cage_result, current_channel="load1_a")
        p = parse_parm(text)
        assert p["COMPASS_MOTCT"] == 2
    else:
        text = px4_params(cage_result, current_channel="load1_a")
        p = parse_qgc(text)
        assert p["CAL_MAG_COMP_TYP"] == 2
    assert "load2_a" in text and "left out" in text  # the second channel cannot be represented
    raw = cage_case.samples.measured_ut
    amps = cage_case.samples.telemetry[:, 0]
    one_channel = np.column_stack([amps, np.zeros_like(amps)])  # load2 off: what the export holds
    want = cal.apply(raw, one_channel)
    field = ardupilot_field_ut if autopilot == "ardupilot" else px4_field_ut
    got = field(p, raw, amps)
    r = assert_equal_up_to_rotation(got, want, cal.correction_matrix, soft_iron(p, autopilot))
    assert left_out_angle_deg(text) == pytest.approx(rotation_angle_deg(r), abs=2e-3)
    # the truth's field, up to R, within the fit's error (0.05 uT noise)
    err = got @ r.T - cage_case.field_ut
    load2_off = cage_case.samples.telemetry[:, 1] == 0
    assert np.sqrt(np.mean(err[load2_off] ** 2)) < 0.2


def test_cage_without_a_current_channel_leaves_every_k_out(cage_result: CalibrationResult) -> None:
    ap, px = ardupilot_params(cage_result), px4_params(cage_result)
    assert not any(name.startswith("COMPASS_MOT") for name in parse_parm(ap))
    assert not any(name.endswith("COMP") or "COMP_TYP" in name for name in parse_qgc(px))
    for text in (ap, px):
        assert "load1_a, load2_a" in text


def test_real_data_end_to_end_through_the_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    parm, params, out = tmp_path / "a" / "mag.parm", tmp_path / "mag.params", tmp_path / "r.json"
    assert main(["calibrate", str(SPHERE), *REAL_ARGS, "--out", str(out), "--ardupilot",
                 str(parm), "--px4", str(params)]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert f"wrote {parm}" in printed and f"wrote {params}" in printed
    res = json.loads(out.read_text())
    w = np.array(res["correction"]["matrix"])
    o = np.array(res["correction"]["offset_ut"])
    raw = 100.0 * np.loadtxt(SPHERE, delimiter=",", skiprows=1)  # G -> uT
    want = (raw - o) @ w.T
    for autopilot, p, field in (
        ("ardupilot", parse_parm(parm.read_text()), ardupilot_field_ut),
        ("px4", parse_qgc(params.read_text()), px4_field_ut),
    ):
        got = field(p, raw, None)
        assert_equal_up_to_rotation(got, want, w, soft_iron(p, autopilot))
        assert np.median(np.linalg.norm(got, axis=1)) == pytest.approx(47.0, rel=0.01)
    # signs and units: offsets (-24.93, 26.74, -67.43) uT
    ap, px = parse_parm(parm.read_text()), parse_qgc(params.read_text())
    np.testing.assert_allclose([ap[f"COMPASS_OFS_{a}"] for a in XYZ], -10.0 * o, rtol=1e-8)
    np.testing.assert_allclose([px[f"CAL_MAG0_{a}OFF"] for a in XYZ], 0.01 * o, rtol=1e-8)
    assert ap["COMPASS_OFS_X"] == pytest.approx(249.3, abs=1.0)  # ArduPilot adds: sign flipped
    assert px["CAL_MAG0_XOFF"] == pytest.approx(-0.2493, abs=1e-3)  # PX4 subtracts: same sign
    assert ap["COMPASS_SCALE"] == 1
    np.testing.assert_allclose(soft_iron(ap, "ardupilot"), soft_iron(px, "px4"), rtol=1e-8)
    # the exported matrix is I + D of the result's Crassidis block
    np.testing.assert_allclose(soft_iron(px, "px4"), np.eye(3) + np.array(res["crassidis"]["D"]),
                               atol=1e-8)  # fmt: skip


def test_other_compass_and_instance_names(cage_result: CalibrationResult) -> None:
    for compass in (2, 3):
        p = parse_parm(ardupilot_params(cage_result, compass, current_channel="load2_a"))
        assert {f"COMPASS_OFS{compass}_X", f"COMPASS_DIA{compass}_Z", f"COMPASS_ODI{compass}_Y",
                f"COMPASS_SCALE{compass}", f"COMPASS_MOT{compass}_Z", "COMPASS_MOTCT"} <= set(p)  # fmt: skip
        assert not any(name.startswith(("COMPASS_OFS_", "COMPASS_DIA_")) for name in p)
        raw = np.array([[10.0, -20.0, 35.0]])
        got = ardupilot_field_ut(p, raw, np.array([2.0]), compass)
        want = cage_result.calibration.apply(raw, np.array([[0.0, 2.0]]))
        np.testing.assert_allclose(np.linalg.norm(got), np.linalg.norm(want), rtol=1e-6)
    p = parse_qgc(px4_params(cage_result, 3))
    assert {f"CAL_MAG3_{a}{g}" for a in XYZ for g in ("OFF", "SCALE", "ODIAG")} == set(p)


# --- units and signs on a hand-made calibration ------------------------------------------------


def with_calibration(result: CalibrationResult, cal: Calibration) -> CalibrationResult:
    return replace(result, calibration=cal)


def made(result: CalibrationResult, sensor: np.ndarray | None = None,
         offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> CalibrationResult:  # fmt: skip
    """``result`` with the calibration ``T = sensor``, ``o = offset`` and no channels."""
    t = np.eye(3) if sensor is None else sensor
    return with_calibration(result, Calibration(t, np.array(offset), np.zeros((0, 3))))


def test_units_and_signs_of_a_known_offset(cage_result: CalibrationResult) -> None:
    cal = Calibration(np.eye(3), np.array([24.94, -3.0, 0.0]), np.array([[2.5, 0.0, -1.0]]),
                      ("i_bat",))  # fmt: skip
    result = with_calibration(cage_result, cal)
    ap = parse_parm(ardupilot_params(result, current_channel="i_bat"))
    px = parse_qgc(px4_params(result, current_channel="i_bat"))
    assert ap["COMPASS_OFS_X"] == pytest.approx(-249.4)  # 24.94 uT = 249.4 mGauss, added
    assert ap["COMPASS_OFS_Y"] == pytest.approx(30.0)
    assert px["CAL_MAG0_XOFF"] == pytest.approx(0.2494)  # 24.94 uT = 0.2494 G, subtracted
    assert px["CAL_MAG0_YOFF"] == pytest.approx(-0.03)
    assert [ap[f"COMPASS_DIA_{a}"] for a in XYZ] == [1, 1, 1]
    assert [ap[f"COMPASS_ODI_{a}"] for a in XYZ] == [0, 0, 0]
    # 2.5 uT/A of bias: -25 mGauss/A (ArduPilot adds), -25 G/kA (PX4 adds before the offset)
    assert [ap[f"COMPASS_MOT_{a}"] for a in XYZ] == pytest.approx([-25.0, 0.0, 10.0])
    assert [px[f"CAL_MAG0_{a}COMP"] for a in XYZ] == pytest.approx([-25.0, 0.0, 10.0])
    raw, amps = np.array([[30.0, 10.0, -40.0]]), np.array([4.0])
    want = cal.apply(raw, amps[:, None])
    np.testing.assert_allclose(ardupilot_field_ut(ap, raw, amps), want, atol=1e-9)
    np.testing.assert_allclose(px4_field_ut(px, raw, amps), want, atol=1e-9)


def test_off_diagonal_names(cage_result: CalibrationResult) -> None:
    """ODI_X/XODIAG is xy, ODI_Y/YODIAG is xz, ODI_Z/ZODIAG is yz."""
    s = np.array([[1.1, 0.02, -0.03], [0.02, 0.95, 0.04], [-0.03, 0.04, 1.05]])
    cal = Calibration.from_correction(s, np.zeros(3))
    result = with_calibration(cage_result, cal)
    ap, px = parse_parm(ardupilot_params(result)), parse_qgc(px4_params(result))
    assert [ap[f"COMPASS_ODI_{a}"] for a in XYZ] == pytest.approx([0.02, -0.03, 0.04])
    assert [px[f"CAL_MAG0_{a}ODIAG"] for a in XYZ] == pytest.approx([0.02, -0.03, 0.04])
    assert [px[f"CAL_MAG0_{a}SCALE"] for a in XYZ] == pytest.approx([1.1, 0.95, 1.05])
    assert left_out_angle_deg(ardupilot_params(result)) == pytest.approx(0.0, abs=1e-3)


# --- refusals -----------------------------------------------------------------------------------


def refused(call: object, *fragments: str) -> None:
    assert callable(call)
    with pytest.raises(ValueError) as info:
        call()
    message = str(info.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, message


def test_refusals(cage_result: CalibrationResult) -> None:
    r = cage_result
    refused(lambda: ardupilot_params(r, 0), "compass must be 1, 2 or 3")
    refused(lambda: ardupilot_params(r, 4), "compass must be 1, 2 or 3")
    refused(lambda: px4_params(r, 4), "instance must be 0 to 3")
    refused(lambda: px4_params(r, -1), "instance must be 0 to 3")
    refused(lambda: ardupilot_params(r, current_channel="nope"), "no telemetry channel 'nope'")
    nan = made(r, offset=(np.nan, 0.0, 0.0))
    refused(lambda: ardupilot_params(nan), "non-finite")
    refused(lambda: px4_params(nan), "non-finite")
    flip = with_calibration(r, Calibration(np.eye(3), np.zeros(3), np.zeros((0, 3)),
                                           rotation=np.diag([1.0, 1.0, -1.0])))  # fmt: skip
    refused(lambda: ardupilot_params(flip), "inverts an axis")
    refused(lambda: px4_params(flip), "inverts an axis")
    # W = 4 I: ArduPilot takes DIA 4 (< 5), PX4's SCALE stops at 3
    four = made(r, 0.25 * np.eye(3))
    assert parse_parm(ardupilot_params(four))["COMPASS_DIA_X"] == pytest.approx(4.0)
    refused(lambda: px4_params(four), "SCALE", "outside [0.1, 3]")
    six = made(r, np.eye(3) / 6.0)
    refused(lambda: ardupilot_params(six), "DIA", "outside (0.2, 5)")
    skew = np.array([[2.0, 1.2, 0.0], [1.2, 2.0, 0.0], [0.0, 0.0, 1.0]])
    odi = with_calibration(r, Calibration.from_correction(skew, np.zeros(3)))
    refused(lambda: ardupilot_params(odi), "ODI", "+-1")
    far = made(r, offset=(400.0, 0.0, 0.0))
    refused(lambda: ardupilot_params(far), "4000 mGauss", "COMPASS_OFFS_MAX")
    assert parse_qgc(px4_params(far))["CAL_MAG0_XOFF"] == pytest.approx(4.0)
    note = made(r, offset=(200.0, 0.0, 0.0))
    assert "raise it to arm" in ardupilot_params(note)  # 2000 mGauss: above the default 1800
    strong = with_calibration(r, Calibration(np.eye(3), np.zeros(3), np.array([[150.0, 0.0, 0.0]]),
                                             ("i",)))  # fmt: skip
    refused(lambda: ardupilot_params(strong, current_channel="i"), "COMPASS_MOT", "1000")


def test_cli_refusal_is_one_line_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, parm = tmp_path / "r.json", tmp_path / "a.parm"
    code = main(["calibrate", str(SPHERE), *REAL_ARGS, "--out", str(out), "--ardupilot", str(parm),
                 "--ardupilot-compass", "5"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "compass must be 1, 2 or 3" in err
    assert not out.exists() and not parm.exists()
    code = main(["calibrate", str(SPHERE), *REAL_ARGS, "--px4", str(tmp_path / "p.params"),
                 "--autopilot-current", "i_bat"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "no telemetry channel 'i_bat'" in err
    code = main(["calibrate", str(SPHERE), *REAL_ARGS, "--autopilot-current", "i_bat"])
    assert code == 2 and "--autopilot-current needs" in capsys.readouterr().err


def test_every_new_option_has_help(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for option in ("--ardupilot FILE.parm write ArduPilot", "--ardupilot-compass N ArduPilot",
                   "--px4 FILE.params write PX4", "--px4-instance N PX4",
                   "--autopilot-current CHANNEL a --telemetry"):  # fmt: skip
        assert option in text


def test_the_guides_autopilot_commands(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """docs/calibration.md's two commands, run from the repository root, outputs in tmp_path."""
    import shlex

    root = SPHERE.parents[3]
    guide = (root / "docs" / "calibration.md").read_text()
    block = re.search(r"<!-- autopilot-example -->\s*```sh\n(.*?)\n```", guide, re.S)
    assert block
    commands = [shlex.split(c) for c in block.group(1).replace("\\\n", " ").splitlines()]
    assert [c[0] for c in commands] == ["rig", "rig"]
    monkeypatch.chdir(root)
    written = {}
    for argv in commands:
        for flag in ("--ardupilot", "--px4"):
            if flag in argv:
                i = argv.index(flag) + 1
                written[flag], argv[i] = tmp_path / argv[i], str(tmp_path / argv[i])
        assert main(["-q", *argv[1:]]) == 0, capsys.readouterr().err
    assert parse_parm(written["--ardupilot"].read_text())["COMPASS_OFS_X"] == pytest.approx(
        249.3, abs=1.0
    )
    assert parse_qgc(written["--px4"].read_text())["CAL_MAG0_XOFF"] == pytest.approx(
        -0.2493, abs=1e-3
    )
