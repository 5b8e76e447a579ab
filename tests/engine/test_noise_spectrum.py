"""The noise_spectrum step: density against synthetic truth, its checks, and a run on the sim."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from rig.procedure.language import ProcedureError, parse_procedure
from rig.steps.noise_spectrum import AROUND_1HZ, amplitude_density, band_mean
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage


def test_white_noise_density_matches_its_variance_and_a_tone_shows_at_its_frequency() -> None:
    """One-sided white density is sigma * sqrt(2 / fs); jittered timestamps (+-3 ms) and a slow
    drift (detrended) must not change it; a 2 Hz tone stands out at 2 Hz only."""
    rng = np.random.default_rng(4)
    fs, sigma, n = 20.0, 0.02, 40_000  # uT
    t = np.arange(n) / fs + rng.uniform(-0.003, 0.003, n)
    xyz = sigma * rng.standard_normal((n, 3)) + 1e-4 * t[:, None]
    xyz[:, 2] += 0.05 * np.sin(2 * math.pi * 2.0 * t)
    f, asd, rate = amplitude_density(t, xyz)
    assert rate == pytest.approx(fs, rel=1e-3)
    expected = sigma * math.sqrt(2.0 / fs)
    band = band_mean(f, asd, (0.1, 1.5))
    assert band[:2] == pytest.approx([expected, expected], rel=0.06)
    assert band_mean(f, asd, AROUND_1HZ)[0] == pytest.approx(expected, rel=0.15)
    tone = band_mean(f, asd, (1.9, 2.1))[2]
    assert tone > 10 * expected and band[2] == pytest.approx(expected, rel=0.1)


def write(tmp_path: Path, step: str) -> Path:
    path = tmp_path / "p.yaml"
    path.write_text(f"procedure: noise\nsteps:\n  - {step}\n    name: spectrum\n")
    return path


def test_a_band_the_hold_cannot_resolve_is_refused(tmp_path: Path) -> None:
    with pytest.raises(
        ProcedureError, match=r"p.yaml:3: step 1 \(noise_spectrum\): hold_s must cover 4 periods"
    ):
        parse_procedure(write(tmp_path, "noise_spectrum: {hold_s: 10, band_hz: [0.1, 5]}"))
    with pytest.raises(ProcedureError, match="band_hz must be"):
        parse_procedure(write(tmp_path, "noise_spectrum: {hold_s: 60, band_hz: [2, 2]}"))


def test_on_the_simulated_cage_the_density_agrees_with_the_noise_floor(tmp_path: Path) -> None:
    """The same nulled DUT: its spectrum's band density and its time-domain standard deviation
    (null_field) describe the same (white) noise: density = std * sqrt(2 / rate) within 30 %."""
    outcome = run_on_sim(
        tmp_path,
        "procedure: noise\nsteps:\n  - null_field: {hold_s: 3}\n    name: floor\n"
        "  - noise_spectrum: {hold_s: 16, band_hz: [0.25, 5]}\n    name: spectrum\n"
        "  - report: {}\n",
    )
    assert outcome.status == "complete", outcome.reason
    spec, floor = outcome.results["spectrum"], outcome.results["floor"]
    assert spec["samples"] > 250 and 15.0 < spec["rate_hz"] < 25.0
    white = floor["dut_noise_nt"] * math.sqrt(2.0 / spec["rate_hz"])
    assert spec["band_density_nt_per_rthz"] == pytest.approx(white, rel=0.3), (spec, floor)
    html = (outcome.folder / "report.html").read_text()
    assert "Noise spectrum &#x27;spectrum&#x27;" in html and "nT/rtHz at 1 Hz" in html
