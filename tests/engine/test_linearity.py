"""The linearity step: its figure against synthetic truth, and a run on the simulated cage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rig.procedure.language import parse_procedure
from rig.procedure.plan import compile_plan, dry_run
from rig.steps.linearity import nonlinearity
from rig.steps.vocabulary import RigTiming
from rig.store.run_store import RunReader
from sim.config import load_config
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage


def test_a_known_quadratic_term_is_found_in_ppm() -> None:
    """reading = 2 + 1.001 h + q h^2 over +-60 uT: h^2 is even, so the fitted line takes only its
    mean; the worst residual is at the ends, q (60^2 - mean(h^2)); gain and offset come back."""
    h = np.linspace(-60.0, 60.0, 13)
    q = 1e-5  # 1/uT
    residual, gain, offset = nonlinearity(h, 2.0 + 1.001 * h + q * h**2)
    worst = np.max(np.abs(residual))
    assert worst == pytest.approx(q * (60.0**2 - np.mean(h**2)), rel=1e-9)
    assert gain == pytest.approx(1.001, abs=1e-9) and offset == pytest.approx(
        2.0 + q * np.mean(h**2)
    )
    assert np.max(np.abs(nonlinearity(h, 1.0 + 0.99 * h)[0])) < 1e-9


def test_the_sweep_goes_to_the_rig_field_limit_unless_given(tmp_path: Path) -> None:
    path = tmp_path / "p.yaml"
    path.write_text("procedure: lin\nsteps:\n  - linearity: {points: 5, dwell_s: 0.5}\n")
    plan = next(compile_plan(parse_procedure(path), RigTiming(max_field_ut=80.0)))
    fields = np.array([c.payload["field_ut"] for c in plan.commands if c.kind == "field"])
    assert fields.shape == (15, 3) and np.abs(fields).max() == 80.0
    assert np.count_nonzero(fields[:5, 1:]) == 0 and fields[0, 0] == -80.0
    report = dry_run(parse_procedure(path), max_field_ut=60.0, timing=RigTiming(max_field_ut=80.0))
    assert report.violations  # a limit of 80 uT on a 60 uT cage is caught before any hardware


def test_on_the_simulated_cage(tmp_path: Path) -> None:
    outcome = run_on_sim(
        tmp_path,
        "procedure: lin\nmagnetometers: {dut: dut, reference: reference}\nsteps:\n"
        "  - linearity: {max_ut: 30, points: 7, dwell_s: 1.0}\n    name: linearity\n  - report: {}\n",
    )
    assert outcome.status == "complete", outcome.reason
    res = outcome.results["linearity"]
    assert res["full_scale_ut"] == 30.0 and set(res["axis_nonlinearity_ppm"]) == {"x", "y", "z"}
    assert all(len(p["applied_ut"]) == 7 for p in res["points"].values())
    # the simulated DUT is linear: what is left is the noise of a 7-sample mean (~10 nT of 30 uT)
    assert 0 < res["nonlinearity_ppm"] < 1500, res["axis_nonlinearity_ppm"]
    truth = load_config().magnetometer("dut")
    for i, axis in enumerate("xyz"):  # the gain along each axis is the DUT's scale factor
        assert res["points"][axis]["gain"][0] == pytest.approx(truth.scale[i], abs=0.01)
    html = (outcome.folder / "report.html").read_text()
    assert "Linearity &#x27;linearity&#x27;" in html and "ppm of" in html


def test_a_field_is_held_until_its_settled_samples_are_in(tmp_path: Path) -> None:
    """Issue 54: 0.02 s of each 0.3 s dwell is settled, too little for the 20 Hz reference's 3
    samples; the engine holds each field longer instead of ending the run with too few points,
    and says so in the run's log."""
    outcome = run_on_sim(
        tmp_path,
        "procedure: lin\nmagnetometers: {dut: dut, reference: reference}\nsteps:\n"
        "  - linearity: {max_ut: 30, points: 5, dwell_s: 0.3, settle_s: 0.28}\n"
        "    name: linearity\n",
    )
    assert outcome.status == "complete", outcome.reason
    res = outcome.results["linearity"]
    assert all(len(p["applied_ut"]) == 5 for p in res["points"].values())
    reader = RunReader(outcome.folder)
    try:
        held = [m for _, level, m in reader.events() if "held longer" in m]
        steps = list(reader.steps())
    finally:
        reader.close()
    assert len(held) == 1 and "15 field(s) held longer" in held[0], held
    (_, _, _, t0, t1) = steps[0]
    assert t1 - t0 > 15 * 0.3 + 15 * 3 / 20.0 * 0.5  # each field held for its samples
