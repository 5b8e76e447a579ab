"""Temperature coefficients of offset (uT/K per axis) and scale (ppm/K) recovered from synthetic
truth within 3 sigma, by the vector and the scalar fit, with the Cramer-Rao bound."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rig.calibration import calibrate
from rig.calibration.residuals import Samples
from rig.calibration.synthetic import THERMAL_OFFSET_PER_K, THERMAL_SCALE_PER_K
from rig.calibration.synthetic import thermal_soak as soak
from rig.errors import CalibrationError

OFFSET_PER_K = THERMAL_OFFSET_PER_K  # uT/K
SCALE_PER_K = THERMAL_SCALE_PER_K  # 1/K
NOISE_UT = 0.05


def thermal_soak(seed: int, n: int = 4000):
    """A sphere of field directions (20-50 uT) recorded while the DUT warms from 10 to 40 C."""
    case = soak(n, seed=seed, noise_ut=NOISE_UT)
    return case.samples.measured_ut, case.field_ut, case.temperature


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


def test_c_header_applies_the_temperature_terms_and_autopilots_name_what_they_leave_out(
    tmp_path: Path,
) -> None:
    """The header's apply() with u[temperature] = T - T_ref gives the field back at 10 and 40 C
    (scale and offset per kelvin included); an ArduPilot file says it leaves the scale term out."""
    import shutil
    import subprocess

    from rig.cli import main

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    m, h, temp_c = thermal_soak(4)
    path = tmp_path / "soak.csv"
    np.savetxt(path, np.column_stack([m, h, temp_c]), delimiter=",", comments="",
               header="mx,my,mz,hx,hy,hz,temp_c", fmt="%.6f")  # fmt: skip
    header, parm = tmp_path / "magcal.h", tmp_path / "mag.parm"
    assert main(["-q", "calibrate", str(path), "--measured", "mx,my,mz", "--field", "hx,hy,hz",
                 "--temperature", "temp_c", "--temperature-ref", "25", "--noise-nt", "50",
                 "--c-header", str(header), "--ardupilot", str(parm)]) == 0  # fmt: skip
    text = header.read_text()
    assert "MAGCAL_SCALE_PER_K" in text and "MAGCAL_TEMPERATURE_REF 25.0f" in text
    # two noise-free readings of a known field at 10 and 40 C
    lower = np.array([[1.02, 0, 0], [0.01, 0.98, 0], [-0.02, 0.015, 1.01]])
    field = np.array([30.0, -20.0, 25.0])
    cases = []
    for t in (10.0, 40.0):
        d_t = t - 25.0  # the truth is about the data's mean; the fit's reference is 25 C
        d_truth = t - float(temp_c.mean())
        reading = (1 + SCALE_PER_K * d_truth) * lower @ field + np.array([3.0, -2.0, 5.0])
        reading += d_truth * OFFSET_PER_K
        cases.append((reading, d_t))
    body = "".join(
        f"  {{ const float m[3] = {{{r[0]:.6f}f, {r[1]:.6f}f, {r[2]:.6f}f}};"
        f" const float u[1] = {{{d:.6f}f}}; float h[3]; magcal_apply(m, u, h);"
        ' printf("%.5f %.5f %.5f\\n", h[0], h[1], h[2]); }\n'
        for r, d in cases
    )
    (tmp_path / "t.c").write_text(
        f'#include <stdio.h>\n#include "magcal.h"\nint main(void) {{\n{body}  return 0;\n}}\n'
    )
    subprocess.run([cc, "-std=c99", "-Wall", "-Werror", "-o", str(tmp_path / "t"),
                    str(tmp_path / "t.c")], check=True)  # fmt: skip
    out = subprocess.run([str(tmp_path / "t")], capture_output=True, text=True, check=True)
    got = np.array(out.stdout.split(), float).reshape(2, 3)
    np.testing.assert_allclose(got, [field, field], atol=0.02)  # noise 0.05 uT, 4000 samples
    assert "# left out: temperature scale coefficient" in parm.read_text()
