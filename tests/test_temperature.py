"""Temperature coefficients of offset (uT/K per axis) and scale (ppm/K) recovered from synthetic
truth within 3 sigma, by the vector and the scalar fit, with the Cramer-Rao bound."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rig.calibration import calibrate
from rig.calibration.residuals import Samples
from rig.errors import CalibrationError

OFFSET_PER_K = np.array([0.04, -0.025, 0.06])  # uT/K
SCALE_PER_K = 300e-6  # 1/K
NOISE_UT = 0.05


def thermal_soak(seed: int, n: int = 4000):
    """A sphere of field directions (20-50 uT) recorded while the DUT warms from 10 to 40 C."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, 3))
    h = u / np.linalg.norm(u, axis=1)[:, None] * rng.uniform(20.0, 50.0, (n, 1))
    temp_c = np.linspace(10.0, 40.0, n) + 0.2 * rng.standard_normal(n)
    d_t = temp_c - temp_c.mean()
    lower = np.array([[1.02, 0, 0], [0.01, 0.98, 0], [-0.02, 0.015, 1.01]])
    offset = np.array([3.0, -2.0, 5.0])
    m = (1 + SCALE_PER_K * d_t)[:, None] * (h @ lower.T) + offset + np.outer(d_t, OFFSET_PER_K)
    m += NOISE_UT * rng.standard_normal((n, 3))
    return m, h, temp_c


@pytest.mark.parametrize("model", ["vector", "ml"])
def test_temperature_coefficients_within_three_sigma(model: str) -> None:
    m, h, temp_c = thermal_soak(1)
    s = (Samples.build(m, field_ut=h) if model == "vector"
         else Samples.build(m, field_magnitude_ut=np.linalg.norm(h, axis=1)))  # fmt: skip
    result = calibrate(s, model, noise_nt=50, temperature=temp_c)
    doc = result.to_dict()
    scale, scale_sigma = (
        doc["temperature"]["scale_per_k"],
        doc["sigma"]["temperature"]["scale_per_k"],
    )
    assert abs(scale - SCALE_PER_K) < 3 * scale_sigma, (scale, scale_sigma)
    assert scale_sigma < 30e-6  # ppm-level on 4000 samples over 30 K
    assert doc["crlb_sigma"]["temperature"]["scale_per_k"] == pytest.approx(scale_sigma, rel=0.15)
    k = np.array(doc["correction"]["k_ut_per_unit"]["temperature"])
    k_sigma = np.array(doc["sigma"]["k_ut_per_unit"]["temperature"])
    assert np.all(np.abs(k - OFFSET_PER_K) < 3 * k_sigma), (k, k_sigma)
    assert doc["temperature"]["reference"] == pytest.approx(float(np.mean(temp_c)))


def test_a_temperature_that_does_not_change_is_refused() -> None:
    m, h, _ = thermal_soak(2, n=500)
    s = Samples.build(m, field_ut=h)
    with pytest.raises(CalibrationError, match=r"less than 0\.5 K"):
        calibrate(s, "vector", temperature=np.full(500, 21.0))


def test_rig_calibrate_temperature_prints_and_writes_the_coefficients(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from rig.cli import main

    m, h, temp_c = thermal_soak(3)
    path = tmp_path / "soak.csv"
    np.savetxt(path, np.column_stack([m, h, temp_c]), delimiter=",", comments="",
               header="mx,my,mz,hx,hy,hz,temp_c", fmt="%.6f")  # fmt: skip
    out = tmp_path / "r.json"
    code = main(["calibrate", str(path), "--measured", "mx,my,mz", "--field", "hx,hy,hz",
                 "--temperature", "temp_c", "--temperature-ref", "25", "--noise-nt", "50",
                 "--out", str(out)])  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    assert "scale per kelvin" in text and "ppm/K" in text and "k[temperature].x" in text
    doc = json.loads(out.read_text())
    assert doc["temperature"]["reference"] == 25.0
    assert (
        abs(doc["temperature"]["scale_per_k"] - SCALE_PER_K)
        < 3 * doc["sigma"]["temperature"]["scale_per_k"]
    )
