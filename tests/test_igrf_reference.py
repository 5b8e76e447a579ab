"""--igrf LAT,LON,ALT_KM,DATE: the reference magnitude from IGRF, as a constant --field-magnitude."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest

from rig.cli import main
from rig.errors import UserInputError
from rig.geomag import igrf_magnitude_ut, parse_igrf_site

DATA = Path(__file__).parent / "data" / "real-magnetometer" / "space-denpa-set1.csv"


def test_igrf_magnitudes_are_the_earths() -> None:
    # the field is ~49.6 uT over the Netherlands and ~32 uT on the equator off West Africa (IGRF)
    assert igrf_magnitude_ut(52.38, 4.64, 0.0, dt.datetime(2026, 11, 25)) == pytest.approx(
        49.6, abs=0.3
    )
    assert igrf_magnitude_ut(0.0, 0.0, 0.0, dt.datetime(2020, 1, 1)) == pytest.approx(31.9, abs=0.3)
    assert igrf_magnitude_ut(52.38, 4.64, 400.0, dt.datetime(2026, 11, 25)) < 45.0  # 400 km up


@pytest.mark.parametrize(
    ("text", "says"),
    [("52,4,0", "LAT,LON,ALT_KM,DATE"), ("x,4,0,2020-01-01", "must be numbers"),
     ("95,4,0,2020-01-01", "latitude"), ("52,4,0,2020-13-01", "YYYY-MM-DD"),
     ("52,4,0,1850-01-01", "1900-2030"), ("52,4,5000,2020-01-01", "altitude")],
)  # fmt: skip
def test_bad_sites_are_one_line_errors(text: str, says: str) -> None:
    with pytest.raises(UserInputError, match=says):
        parse_igrf_site(text)


def test_igrf_reference_equals_the_same_constant_magnitude(tmp_path: Path) -> None:
    site = "35.7,139.7,0.04,2020-06-01"
    b_ut = igrf_magnitude_ut(35.7, 139.7, 0.04, dt.datetime(2020, 6, 1))
    common = ["calibrate", str(DATA), "--measured", "x,y,z", "--unit", "G", "-q"]
    assert main([*common, "--igrf", site, "--out", str(tmp_path / "a.json")]) == 0
    assert (
        main(
            [*common, "--field-magnitude", f"{b_ut / 100:.12g}", "--out", str(tmp_path / "b.json")]
        )
        == 0
    )
    a, b = (json.loads((tmp_path / f).read_text()) for f in ("a.json", "b.json"))
    assert a["correction"]["offset_ut"] == pytest.approx(b["correction"]["offset_ut"], rel=1e-9)
    assert main([*common, "--igrf", "52,4,0"]) == 2
