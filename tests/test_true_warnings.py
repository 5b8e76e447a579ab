"""Warnings and exported comments say what is true: the offset-to-channel correlation and how to
break it; a scalar fit's left-out rotation is not a mounting; unit slips are refused (issue 34)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rig.calibration import Calibration, Samples, calibrate
from rig.calibration.synthetic import cage_like
from rig.cli import main

SPHERE = Path(__file__).resolve().parent / "data" / "real-magnetometer" / "space-denpa-set1.csv"


def with_channel(u: np.ndarray) -> Samples:
    """A cage sweep whose one load channel is ``u`` (A)."""
    case = cage_like(3000, seed=21, channels=1)
    t = case.truth
    truth = Calibration(t.sensor, t.offset_ut, t.k_ut_per_unit, ("load_bus",), t.rotation)
    noise = 0.05 * np.random.default_rng(3).standard_normal((u.size, 3))
    m = truth.predict(case.field_ut, u[:, None]) + noise
    return Samples.build(m, field_ut=case.field_ut, telemetry=u[:, None], channels=("load_bus",))


def offset_warnings(s: Samples) -> list[str]:
    result = calibrate(s, "vector", noise_nt=50.0)
    return [w for w in result.warnings if "0 and k[load_bus]" in w]


def test_a_channel_that_reaches_zero_rarely_is_not_said_never_to() -> None:
    u = np.full(3000, 3.0) + 0.01 * np.sin(np.arange(3000))
    u[1000:1060] = 0.0  # 2 % of the samples at zero
    warnings = offset_warnings(with_channel(u))
    assert warnings, "the offset and the coefficient correlate: say so"
    assert all("never" not in w for w in warnings), warnings
    assert any("near zero in 2 % of the samples" in w and "r = " in w for w in warnings), warnings


def test_a_channel_that_never_reaches_zero_is_named() -> None:
    u = 2.5 + np.random.default_rng(4).uniform(0.0, 1.0, 3000)
    warnings = offset_warnings(with_channel(u))
    assert any("never returns near zero (min |u| = 2.5" in w for w in warnings), warnings


def test_a_channel_at_zero_half_the_time_draws_no_warning() -> None:
    u = np.where(np.arange(3000) % 600 < 300, 0.0, 3.0)
    assert offset_warnings(with_channel(u)) == []


def test_a_scalar_fits_rotation_is_not_offered_as_a_mounting(tmp_path: Path) -> None:
    args = ["-q", "calibrate", str(SPHERE), "--measured", "x,y,z", "--unit", "G",
            "--field-magnitude", "0.47"]  # fmt: skip
    parm, params = tmp_path / "m.parm", tmp_path / "m.params"
    assert main([*args, "--ardupilot", str(parm), "--px4", str(params)]) == 0
    for text, name in ((parm.read_text(), "COMPASS_ORIENT"), (params.read_text(), "CAL_MAG0_ROT")):
        line = next(x for x in text.splitlines() if x.startswith("# left out: rotation"))
        assert "not the mounting" in line and f"do not set {name} from it" in line, line


@pytest.mark.parametrize(
    ("extra", "said"),
    [
        (["--unit", "G", "--field-magnitude", "47"],
         "47 G is 4700 uT, 67.1 times the strongest Earth field (70 uT)"),
        (["--field-magnitude", "0.47"],
         "0.47 uT is 1/42.6 of the weakest Earth field (20 uT)"),
        (["--unit", "G", "--field-magnitude", "4.7"], "a scale of 0.199"),
    ],
)  # fmt: skip
def test_an_implausible_field_names_both_readings(
    extra: list[str], said: str, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    args = ["calibrate", str(SPHERE), "--measured", "x,y,z", *extra]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and said in err and "--allow-implausible-field" in err, err
    if "47" in extra:
        assert "did you mean 47 uT? pass --field-unit uT" in err, err
    if "0.47" in extra:
        assert "did you mean 0.47 G? pass --unit G" in err, err
    assert main(["-q", *args, "--allow-implausible-field"]) == 0
