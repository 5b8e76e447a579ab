"""The stability step through the wire protocols on the simulated cage: a DUT whose offset
drifts (the simulator's truth) held at null field for a minute, the reference subtracted."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from sim.config import load_config
from tests.simrun import run_on_sim

DRIFT_NT_PER_H = (1200.0, 0.0, -1200.0)  # 20 nT a minute: seen within a 60 s hold


@pytest.mark.slow
def test_a_drifting_dut_held_for_a_minute_shows_its_drift_and_allan_deviation(
    tmp_path: Path,
) -> None:
    cfg = load_config()
    mags = tuple(dataclasses.replace(m, offset_drift_nt_per_h=DRIFT_NT_PER_H)
                 if m.name == "dut" else m for m in cfg.magnetometers)  # fmt: skip
    outcome = run_on_sim(
        tmp_path,
        "procedure: stability\nmagnetometers: {dut: dut, reference: reference}\nsteps:\n"
        "  - null_field: {hold_s: 3}\n    name: floor\n"
        "  - stability: {hold_s: 60, settle_s: 1}\n    name: offset stability\n"
        "  - report: {}\n",
        sim_config=dataclasses.replace(cfg, magnetometers=mags),
    )
    assert outcome.status == "complete", outcome.reason
    r = outcome.results["offset stability"]
    assert r["reference_note"] == "the reference magnetometer 'reference' subtracted"
    truth = 12.0 * np.asarray(DRIFT_NT_PER_H)
    z = (np.asarray(r["drift_nt_per_12h"]) - truth) / np.asarray(r["drift_sigma_nt_per_12h"])
    assert np.all(np.abs(z) < 3.5), (r["drift_nt_per_12h"], r["drift_sigma_nt_per_12h"])
    assert r["drift_nt_per_12h"][0] > 3 * r["drift_sigma_nt_per_12h"][0]  # seen, not noise
    # at 1 s: the white noise of the DUT less the reference (the null field's paired noise)
    paired = outcome.results["floor"]["dut_paired_noise_nt"]
    rate = r["allan"]["rate_hz"]
    assert np.asarray(r["adev_1s_nt"]) == pytest.approx(paired / np.sqrt(rate), rel=0.5)
    html = (outcome.folder / "report.html").read_text()
    assert "Offset stability (&#x27;offset stability&#x27;): Allan deviation" in html
