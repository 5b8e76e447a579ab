"""Orbit replay geometry: sgp4 + IGRF frames, sun and eclipse, panel currents, the plan, and the
tracked samples it yields on a slow link."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest

from rig.analysis import calibration_data
from rig.procedure.language import parse_procedure
from rig.procedure.plan import compile_plan
from rig.procedure_files import find_procedure
from rig.steps.orbit import geodetic, orbit_track, panel_current, sun_direction_eci
from rig.store import RunReader
from tests.simrun import run_on_sim

pytestmark = pytest.mark.simcage

ISS = (
    "1 25544U 98067A   19343.69339541  .00001764  00000-0  38792-4 0  9991",
    "2 25544  51.6439 211.2001 0007417  17.6667  85.6398 15.50103472202482",
)
START = dt.datetime(2019, 12, 9, 12, 0, 0)


def test_geodetic_of_known_points() -> None:
    lat, lon, h = geodetic(np.array([[6378.137, 0.0, 0.0], [0.0, 0.0, 6356.7523142 + 100.0]]))
    np.testing.assert_allclose(lat, [0.0, 90.0], atol=1e-9)
    np.testing.assert_allclose(h, [0.0, 100.0], atol=1e-6)
    assert lon[0] == pytest.approx(0.0)


def test_field_magnitude_matches_igrf_and_frames_preserve_it() -> None:
    import ppigrf

    t = np.arange(0.0, 5600.0, 60.0)
    for attitude in ("inertial", "nadir", "tumbling"):
        track = orbit_track(*ISS, START, t, attitude)
        mag = np.linalg.norm(track.field_body_ut, axis=1)
        assert mag.min() > 18.0 and mag.max() < 60.0  # LEO at 51.6 deg inclination
    from sgp4.api import Satrec, jday
    from sgp4.propagation import gstime

    sat = Satrec.twoline2rv(*ISS)
    jd, fr = jday(2019, 12, 9, 12, 0, 0)
    _, r, _ = sat.sgp4(jd, fr)
    np.testing.assert_allclose(
        r, [3520.604, -2626.766, 5174.4], atol=0.01
    )  # verified reference value
    g = gstime(jd + fr)
    r_ecef = np.array(
        [np.cos(g) * r[0] + np.sin(g) * r[1], -np.sin(g) * r[0] + np.cos(g) * r[1], r[2]]
    )
    lat, lon, h = geodetic(r_ecef[None, :])
    be, bn, bu = ppigrf.igrf(lon, lat, h, START)
    expected = float(np.sqrt(be**2 + bn**2 + bu**2).ravel()[0]) / 1000
    track = orbit_track(*ISS, START, np.array([0.0]), "inertial")
    assert np.linalg.norm(track.field_body_ut[0]) == pytest.approx(expected, rel=1e-6)


def test_sun_eclipse_and_panels() -> None:
    s = sun_direction_eci(np.array([2451545.0 + 171.0]))[0]  # near the June solstice
    assert s[2] == pytest.approx(np.sin(np.radians(23.44)), abs=0.01)
    track = orbit_track(*ISS, START, np.arange(0.0, 5560.0, 10.0), "nadir")
    assert 0.55 < track.sunlit.mean() < 0.75  # ISS: roughly a third of each orbit in shadow
    amps = panel_current(track, "+y", 1.5)
    assert amps.max() <= 1.5 and np.all(amps[~track.sunlit] == 0.0)


def test_orbit_procedure_plans_field_and_panel_commands() -> None:
    proc = parse_procedure(find_procedure("orbit-replay"))
    plan = next(p for p in compile_plan(proc) if p.step.kind == "orbit_replay")
    fields = [c for c in plan.commands if c.kind == "field"]
    loads = [c for c in plan.commands if c.kind == "load"]
    assert len(fields) == 90 * 50 and all(c.payload["track"] for c in fields)
    assert {c.payload["channel"] for c in loads} == {"load_bus", "load_panel"}
    assert loads and max(c.payload["current_a"] for c in loads) <= 2.0


ORBIT_ONLY = """
procedure: tracked field over a slow link
magnetometers: {dut: dut, reference: reference}
steps:
  - orbit_replay:
      tle:
        - "1 25544U 98067A   19343.69339541  .00001764  00000-0  38792-4 0  9991"
        - "2 25544  51.6439 211.2001 0007417  17.6667  85.6398 15.50103472202482"
      start: "2019-12-09T12:00:00Z"
      duration_s: 3
      time_scale: 10
      rate_hz: 20
      attitude: tumbling
      tumble_deg_s: 3
    name: orbit
"""


def test_a_slow_supply_link_does_not_cost_the_tracked_samples(tmp_path: Path) -> None:
    """Each tracked set-point takes longer than the 50 ms between set-points (a 60 ms reply delay
    on coil_x): the field is still the one the reference follows, so the calibration keeps the DUT
    samples taken while set-points were being written (CI lost 98 % of them this way)."""
    outcome = run_on_sim(tmp_path, ORBIT_ONLY, reply_delay_s={"coil_x": 0.06})
    assert outcome.status == "complete", outcome.reason
    reader = RunReader(outcome.folder)
    try:
        ((_, _, _, t0, t1),) = reader.steps()
        busy = sum(
            t - float(p["t_issued"]) for t, _, kind, p in reader.commands() if kind == "field"
        )
        in_step = sum(t0 <= s[0] <= t1 for s in reader.samples("dut"))
        samples, _, unresolved, *_ = calibration_data(reader, "dut", "reference", [], ["orbit"], 0.0,
                                                  None)  # fmt: skip
    finally:
        reader.close()
    assert in_step > 100
    # kept, or left out only where the late coil_x made the field jump between reference samples
    assert samples.n + unresolved >= 0.75 * in_step, (samples.n, unresolved, in_step, busy)
    # late set-points make the field jump; beside two CPU hogs they are late more often (190 of
    # 444 kept once): the floor says the jump rule does not leave out everything
    assert samples.n >= 0.35 * in_step, (samples.n, unresolved, in_step, busy)
