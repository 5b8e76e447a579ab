"""The ``closed_loop`` step kind with a fake run context (issue 56): its plan (the starting field,
the loop, its end), what it refuses, and the loop itself on simulated time against a perfect cage
(the DUT reads exactly the last field commanded, plus noise): then the closed loop is the
all-software run, and a DUT with a known offset and scale error read raw changes it by what
that error does to the same software run, read calibrated not at all."""

from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import timebase
from rig.errors import RigError
from rig.hil.dynamics import Spacecraft
from rig.hil.flight_software import BDot, default_gain
from rig.hil.loop import LoopPlan, OrbitField, software_only
from rig.hil.torque_rods import RodLog, TorqueRods, stray_bias_ut
from rig.steps import KINDS
from rig.steps.closed_loop_run import mrp_to_dcm, scenario_of
from rig.steps.vocabulary import FieldCommand, ProcedureError
from tests.steps.fake_context import FakeContext, compile_step, make_procedure, make_step

TLE = [
    "1 25544U 98067A   19343.69339541  .00001764  00000-0  38792-4 0  9991",
    "2 25544  51.6439 211.2001 0007417  17.6667  85.6398 15.50103472202482",
]
LOOP = {"tle": TLE, "start": "2019-12-09T12:00:00Z", "time_scale": 30, "duration_s": 120,
        "rate_hz": 10, "control_hz": 2, "inertia_kg_m2": [0.001, 0.001, 0.0008],
        "max_dipole_am2": 0.2, "rate_deg_s": [5.77, 5.77, 5.77], "until_deg_s": 4,
        "noise_nt": 20}  # fmt: skip
"""A small spacecraft at 10 deg/s in a field turning 30 times faster than in orbit: it detumbles
below 4 deg/s in about a minute."""


def test_the_plan_makes_the_starting_field_then_hands_the_time_to_the_loop() -> None:
    step = make_step("closed_loop", LOOP)
    cmds, duration = compile_step(step)
    assert duration == 120.0
    assert [(c.t_s, c.kind) for c in cmds] == [(0.0, "field"), (0.0, "closed_loop"), (120.0, "end")]
    scenario = scenario_of(step.params)
    start = mrp_to_dcm(np.array(scenario.craft.mrp)) @ scenario.orbit.at(0.0)
    assert cmds[0].payload["field_ut"] == pytest.approx(list(start))
    assert not cmds[0].payload.get("track")  # ramped there and settled, not tracked
    assert 15.0 < np.linalg.norm(start) < 65.0  # the geomagnetic field in low Earth orbit
    # rig check may meet any direction at the orbit's largest field
    assert KINDS["closed_loop"].field_envelope_ut(step) == pytest.approx(scenario.orbit.peak_ut)
    half = make_step("closed_loop", {**LOOP, "field_scale": 0.5})
    assert KINDS["closed_loop"].field_envelope_ut(half) == pytest.approx(
        0.5 * scenario.orbit.peak_ut
    )


def test_mrp_to_dcm_is_a_rotation_and_matches_a_quarter_turn() -> None:
    c = mrp_to_dcm(np.array([0.0, 0.0, np.tan(np.pi / 8)]))  # 90 deg about z
    assert c @ np.array([1.0, 0.0, 0.0]) == pytest.approx([0.0, -1.0, 0.0], abs=1e-12)
    r = mrp_to_dcm(np.array([0.1, 0.2, -0.1]))
    assert r @ r.T == pytest.approx(np.eye(3), abs=1e-12) and np.linalg.det(r) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("change", "says"),
    [
        ({"control_hz": 20, "rate_hz": 10}, "control_hz must not exceed rate_hz"),
        ({"tle": TLE[:1]}, "'tle' must be the two TLE lines"),
        ({"start": "noon"}, "not an ISO date-time"),
        ({"inertia_kg_m2": [0.01, 0.0, 0.01]}, "every principal moment of inertia must be > 0"),
        ({"rate_deg_s": [400, 0, 0]}, "'rate_deg_s' must be at most 360 deg/s on each axis"),
        ({"readings": "cooked"}, "'readings'"),
    ],
)
def test_refused_with_the_fix(change: dict[str, Any], says: str) -> None:
    with pytest.raises(ProcedureError, match=says):
        make_step("closed_loop", {**LOOP, **change})


def test_calibrated_readings_need_a_calibration_earlier(tmp_path: Path) -> None:
    step = make_step("closed_loop", {**LOOP, "readings": "calibrated"})
    ctx = FakeContext(make_procedure(step), tmp_path)
    with pytest.raises(RigError, match="needs a calibration earlier in the run"):
        KINDS["closed_loop"].execution(ctx, step)


class PerfectCage:
    """The DUT reads the field last commanded (the cage makes it at once), as ``dut(field)``
    plus white noise, at 20 Hz on the run's clock."""

    def __init__(self, ctx: FakeContext, dut: Any, noise_ut: float, seed: int) -> None:
        self.ctx, self.dut, self.noise = ctx, dut, noise_ut
        self.rng = np.random.default_rng(seed)
        self.stop = timebase.Event()
        self.thread = timebase.Thread(self._run, name="perfect-cage", daemon=True)

    def _run(self) -> None:
        while not self.stop.wait(0.05):
            fields = [p["field_ut"] for _, kind, p in self.ctx.sent if kind == "field"]
            if fields:
                reading = self.dut(np.array(fields[-1])) + self.rng.normal(0, self.noise, 3)
                for listener in list(self.ctx.samplers["dut"].listeners):
                    listener(timebase.monotonic(), tuple(float(v) for v in reading))


def closed_loop_on_a_perfect_cage(tmp_path: Path, body: dict[str, Any], dut: Any,
                                  results: dict[str, Any] | None = None) -> dict[str, Any]:  # fmt: skip
    """The step's execution on simulated time against :class:`PerfectCage`; its result."""
    step = make_step("closed_loop", body, name="detumble")
    tmp_path.mkdir(parents=True, exist_ok=True)
    ctx = FakeContext(make_procedure(step), tmp_path, results=dict(results or {}))
    with timebase.simulated():
        cage = PerfectCage(ctx, dut, 0.02, seed=3)
        execution = KINDS["closed_loop"].execution(ctx, step)
        start = FieldCommand(0.0, {"field_ut": list(scenario_of(step.params).initial_field_ut())})
        ctx.command(0, start, 0.0)
        cage.thread.start()
        execution.run({})
        assert execution.stop is not None
        execution.stop.wait(float(body["duration_s"]) + 1.0)
        execution.wind_down()
        cage.stop.set()
        execution.finish(0.0, timebase.monotonic())
    return ctx.results["detumble"]


def software_detumble_s(dut: Any, body: dict[str, Any], seed: int = 0) -> float | None:
    """The all-software run with the DUT's own error in its model magnetometer."""
    scenario = scenario_of(make_step("closed_loop", body).params)

    class Seen(BDot):
        def dipole(self, field_ut: Any, t_s: float) -> Any:
            return super().dipole(dut(np.asarray(field_ut)), t_s)

    dipole = scenario.craft.max_dipole_am2
    return software_only(scenario.craft, scenario.plan, scenario.orbit,
                         Seen(default_gain(dipole), dipole), 0.02, 20.0, seed)[1]  # fmt: skip


def test_on_a_perfect_cage_the_closed_loop_is_the_software_run(tmp_path: Path) -> None:
    result = closed_loop_on_a_perfect_cage(tmp_path, LOOP, lambda b: b)
    assert result["detumble_s"] is not None and result["software_detumble_s"] is not None
    assert abs(result["difference_pct"]) < 10.0, result["summary"]
    assert result["late_ticks"] == 0 and result["ticks"] == round(result["detumble_s"] * 10) + 1
    # a reading reaches the cage at the tick after its period ends: within a tick and a sample
    assert 0.0 < result["latency_ms"]["p99"] <= 100.0 + 50.0 + 1e-6
    with (tmp_path / result["history_file"]).open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == result["ticks"]
    rates = [np.linalg.norm([float(r[f"rate_{a}_deg_s"]) for a in "xyz"]) for r in rows]
    assert rates[0] == pytest.approx(10.0, abs=0.01) and rates[-1] <= 4.0


# a DUT mounted turned 60 deg about z, with 2 uT of offset on z: B-dot differences the field, so
# the offset drops out, but the dipoles go out turned (the detumble takes about 68 s, not 56)
TURN = np.array([[np.cos(1.0472), -np.sin(1.0472), 0.0], [np.sin(1.0472), np.cos(1.0472), 0.0],
                 [0.0, 0.0, 1.0]])  # fmt: skip


def miscalibrated(b: Any) -> Any:
    return TURN @ b + np.array([0.0, 0.0, 2.0])


CORRECTION = {"vector calibration": {
    "model": "vector", "method": "test", "samples": 100, "channels": [],
    "correction": {"matrix": TURN.T.tolist(), "offset_ut": [0.0, 0.0, 2.0], "k_ut_per_unit": {}},
    "springmann": {"a": 1.0, "b": 1.0, "c": 1.0, "x0_ut": 0.0, "y0_ut": 0.0, "z0_ut": 2.0,
                   "rho_deg": 0.0, "phi_deg": 0.0, "lambda_deg": 0.0},
    "residual_rms_nt": 10.0}}  # fmt: skip


def test_a_miscalibrated_dut_read_raw_changes_the_loop_as_its_error_predicts_and_calibrated_not(
    tmp_path: Path,
) -> None:
    longer = {**LOOP, "duration_s": 240}
    raw = closed_loop_on_a_perfect_cage(tmp_path / "raw", longer, miscalibrated)
    predicted = software_detumble_s(miscalibrated, longer)
    assert raw["detumble_s"] is not None and predicted is not None
    assert raw["detumble_s"] == pytest.approx(predicted, rel=0.10)
    assert raw["difference_pct"] > 15.0  # slower than the software run with a perfect sensor
    fixed = closed_loop_on_a_perfect_cage(tmp_path / "cal", {**LOOP, "readings": "calibrated"},
                                          miscalibrated, CORRECTION)  # fmt: skip
    assert fixed["readings"] == "calibrated"
    assert abs(fixed["difference_pct"]) < 10.0, fixed["summary"]
    print(
        f"raw {raw['detumble_s']:.1f} s (software with the same error {predicted:.1f} s),"
        f" calibrated {fixed['detumble_s']:.1f} s (software {fixed['software_detumble_s']:.1f} s)"
    )


def test_bdot_takes_energy_out_and_clips_each_rod() -> None:
    bdot = BDot(gain_am2_per_ut_s=1.0, max_dipole_am2=0.2)
    assert bdot.dipole(np.array([30.0, 0.0, 0.0]), 0.0) == pytest.approx([0.0, 0.0, 0.0])
    m = bdot.dipole(np.array([30.0, 0.5, -0.05]), 0.5)  # dB/dt = (0, 1, -0.1) uT/s
    assert m == pytest.approx([0.0, -0.2, 0.1])


def test_the_software_run_detumbles_and_is_deterministic() -> None:
    scenario = scenario_of(make_step("closed_loop", LOOP).params)
    craft, plan = scenario.craft, scenario.plan
    runs = [software_only(craft, plan, scenario.orbit, scenario.software(), 0.02, 20.0, 7)
            for _ in range(2)]  # fmt: skip
    (ticks, detumble), (again, _) = runs
    assert detumble is not None and detumble < plan.duration_s
    assert [t.rate_deg_s.tolist() for t in ticks] == [t.rate_deg_s.tolist() for t in again]
    still = OrbitField(scenario.orbit.t_orbit_s, scenario.orbit.field_ut, 0.0)
    none = software_only(craft, LoopPlan(10, 2, 20, 4), still, BDot(0.0, 0.2), 0.0, 20.0)
    assert isinstance(craft, Spacecraft) and none[1] is None  # no gain: it keeps tumbling


def test_only_the_dynamics_module_imports_basilisk_and_a_rig_without_it_says_how_to_install() -> (
    None
):
    import subprocess
    import sys

    rig_dir = Path(__file__).resolve().parents[2] / "rig"
    importers = sorted(str(p.relative_to(rig_dir.parent)) for p in rig_dir.rglob("*.py")
                       if re.search(r"^\s*(from|import) Basilisk\b", p.read_text(), re.M))  # fmt: skip
    assert importers == ["rig/hil/dynamics.py"], importers
    probe = (
        "import sys\n"
        "import rig.cli, rig.engine.runner, rig.steps, rig.report.acceptance\n"
        "assert not any(m.startswith('Basilisk') for m in sys.modules), 'Basilisk imported'\n"
        "sys.modules['Basilisk'] = None  # as on a rig without the hil extra\n"
        "from rig.hil.dynamics import BasiliskDynamics, DynamicsUnavailableError, Spacecraft\n"
        "try:\n"
        "    BasiliskDynamics(Spacecraft(((1, 0, 0), (0, 1, 0), (0, 0, 1)), 0.2, (0, 0, 0)), 0.1)\n"
        "except DynamicsUnavailableError as exc:\n"
        "    print(exc)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == (
        "the closed loop needs Basilisk, which is not installed: pip install -e '.[hil]'"
        " (Basilisk, the package 'bsk')"
    )


RODS = {**LOOP, "torque_rods": ["load_bus", "none", "load_panel"], "rod_a_per_am2": 5.0,
        "rod_bias_a": 1.0}  # fmt: skip
LOADS = ("load_bus", "load_panel")


def test_rods_on_loads_start_at_their_bias_and_rig_check_meets_their_largest_current() -> None:
    step = make_step("closed_loop", RODS, loads=LOADS)
    cmds, _ = compile_step(step)
    assert [(c.kind, c.payload.get("channel"), c.payload.get("current_a")) for c in cmds[:4]] == [
        ("field", None, None), ("load", "load_bus", 1.0), ("load", "load_panel", 1.0),
        ("closed_loop", None, None)]  # fmt: skip
    assert KINDS["closed_loop"].load_envelope_a(step) == {"load_bus": 2.0, "load_panel": 2.0}
    assert KINDS["closed_loop"].load_envelope_a(make_step("closed_loop", LOOP)) == {}
    rods = TorqueRods.of(step.params)
    assert rods is not None and rods.used == LOADS
    # x's dipole on load_bus, z's on load_panel; the y rod is not on a load
    assert rods.currents_a([0.2, -0.1, -0.2]) == {"load_bus": 2.0, "load_panel": 0.0}
    assert rods.currents_a([-0.05, 0.0, 0.1]) == {"load_bus": 0.75, "load_panel": 1.5}


def test_the_rods_currents_are_known_at_each_readings_date_and_their_bias_subtracts() -> None:
    log = RodLog()
    assert log.at(5.0) == {}
    log.add(1.0, {"load_bus": 1.0})
    log.add(2.0, {"load_bus": 1.5})
    assert log.at(0.5) == {} and log.at(1.0) == {"load_bus": 1.0}
    assert log.at(1.99) == {"load_bus": 1.0} and log.at(7.0) == {"load_bus": 1.5}
    k = {"load_bus": np.array([0.9, -0.3, 0.4]), "load_panel": np.array([0.0, 0.6, 0.0])}
    assert stray_bias_ut(k, {"load_bus": 2.0}) == pytest.approx([1.8, -0.6, 0.8])
    assert stray_bias_ut(k, {"load_bus": 1.0, "load_panel": 0.5, "other": 9.0}) == pytest.approx(
        [0.9, 0.0, 0.4]
    )


@pytest.mark.parametrize(
    ("change", "says"),
    [
        ({"torque_rods": ["load_bus", "load_panel"]}, "three names"),
        ({"torque_rods": ["none", "none", "none"]}, "names no load channel"),
        ({"torque_rods": ["load_bus", "load_bus", "none"]}, "names a load channel twice"),
        ({"torque_rods": ["load_bus", "heater", "none"]}, "'heater' is not one of the procedure's"),
        ({"rod_a_per_am2": 0.0}, "'rod_a_per_am2' .* must be > 0 with rods"),
        ({"rod_bias_a": 0.5}, "'rod_bias_a' 0.5 A is below the 1 A a rod's largest dipole"),
    ],
)
def test_rods_refused_with_the_fix(change: dict[str, Any], says: str) -> None:
    with pytest.raises(ProcedureError, match=says):
        make_step("closed_loop", {**RODS, **change}, loads=LOADS)


def test_calibrated_readings_with_rods_need_their_channels_fitted(tmp_path: Path) -> None:
    step = make_step("closed_loop", {**RODS, "readings": "calibrated"}, loads=LOADS)
    ctx = FakeContext(make_procedure(step, loads=LOADS), tmp_path, results=dict(CORRECTION))
    with pytest.raises(RigError, match="torque rod on load_bus needs a calibration that fitted"):
        KINDS["closed_loop"].execution(ctx, step)


def test_the_report_says_what_the_hardware_changed_and_how_the_loop_ran() -> None:
    result = {"detumble_s": 66.7, "software_detumble_s": 56.0, "difference_pct": 19.1,
              "final_rate_deg_s": 3.9, "until_deg_s": 4.0, "noise_nt": 21.3, "ticks": 668,
              "late_ticks": 2, "latency_ms": {"p50": 50.0, "p99": 27.0, "max": 80.0},
              "readings": "raw", "flight_software": "B-dot in process", "field_model": "IGRF",
              "dynamics": "Basilisk", "torque_rods": {"channels": ["load_bus", "none", "load_panel"],
              "a_per_am2": 7.5, "bias_a": 1.5, "changes": 40},
              "flight_computer": {"answered": 130, "missed": 2, "problem": "no answer within 100 ms",
                                  "round_trip_ms_p99": 13.0}}  # fmt: skip
    lines = KINDS["closed_loop"].report_lines("detumble", result)
    assert lines[0] == (
        "Detumble below 4 deg/s: through the cage 66.7 s; all in software (the same scenario, a"
        " model magnetometer with 21.3 nT of noise) 56.0 s; the hardware changed it by +19.1 %."
    )
    text = "\n".join(lines)
    assert "668 ticks, 2 late" in text and "p99 27 ms" in text and "readings raw" in text
    assert "load_bus, none, load_panel (x, y, z): 1.5 A + 7.5 A per A m^2" in text
    assert "130 answers, 2 missed (first: no answer within 100 ms); round trip p99 13.0 ms" in text
    never = {**result, "detumble_s": None, "difference_pct": None, "torque_rods": None,
             "flight_computer": None}  # fmt: skip
    lines = KINDS["closed_loop"].report_lines("detumble", never)
    assert lines[0].startswith("Detumble below 4 deg/s: through the cage not reached (3.90 deg/s")
    assert len(lines) == 3 and KINDS["closed_loop"].report_lines("detumble", "junk") == []


def test_the_3u_bench_runs_the_shipped_procedure_with_a_3u_cubesat(tmp_path: Path) -> None:
    """docs/hil.md's ``bench/bench_closed_loop_3u.py``: the shipped procedure with the step's
    default spacecraft (a 3U CubeSat) in the orbit's own field, without the small craft's check."""
    from bench.bench_closed_loop_3u import procedure
    from rig.procedure.language import parse_procedure

    path = tmp_path / "cubesat.yaml"
    path.write_text(procedure(2.0, 5.0, 14400.0))
    proc = parse_procedure(path)
    (loop,) = [s for s in proc.steps if s.kind == "closed_loop"]
    assert loop.params["inertia_kg_m2"] == [0.0333, 0.0333, 0.0067]
    assert loop.params["max_dipole_am2"] == 0.2 and loop.params["time_scale"] == 1.0
    assert (loop.params["until_deg_s"], loop.params["rate_hz"]) == (2.0, 5.0)
    assert [s.kind for s in proc.steps][-1] == "report" and "check" not in {
        s.kind for s in proc.steps
    }
