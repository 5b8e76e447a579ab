"""What each step kind compiles to: its field and load set-points, its own command, its duration."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from rig.steps import KINDS
from rig.steps.characterize_cage import characterization_duration_s
from rig.steps.load_profiles import LOAD_PROFILES
from rig.steps.vocabulary import (
    DEFAULT_FIELD_LIMIT_UT,
    ActionCommand,
    Command,
    EndCommand,
    FieldCommand,
    ProcedureError,
    RigTiming,
    bind_params,
)
from tests.steps.fake_context import compile_step, make_step
from tests.steps.test_step_params import ORBIT


def fields_of(cmds: list[Command]) -> tuple[list[float], np.ndarray]:
    """Times (s) and fields (N, 3) uT of the field commands."""
    rows = [(c.t_s, c.payload["field_ut"]) for c in cmds if c.kind == "field"]
    return [t for t, _ in rows], np.array([f for _, f in rows], float).reshape(-1, 3)


@pytest.mark.parametrize(
    ("kind", "body"),
    [
        ("prompt", "Mount the DUT"),
        ("report", None),
        ("calibrate", {"steps": ["sweep"]}),
        ("check", {"criteria": [{"result": "a", "value": "b", "max": 1}]}),
        ("characterize_cage", {"amplitude_a": 0.5}),
        ("coil_axes", {"amplitude_a": 0.5}),
        ("coil_scalar", {"directions": 20}),
        ("field_map", {"amplitude_a": 0.5}),
    ],
)
def test_an_action_step_is_one_command_of_its_own_carrying_its_parameters(
    kind: str, body: object
) -> None:
    step = make_step(kind, body)
    cmds, _ = compile_step(step)
    assert cmds == [ActionCommand(0.0, kind, step.params)]


def test_null_field_nulls_then_holds() -> None:
    cmds, duration = compile_step(make_step("null_field", {"hold_s": 3}))
    assert duration == 3.0
    assert cmds == [
        FieldCommand(0.0, {"field_ut": [0.0, 0.0, 0.0], "trim": False}),
        EndCommand(3.0),
    ]
    trimmed, _ = compile_step(make_step("null_field", {"trim": "yes"}))
    assert trimmed[0].payload["trim"] is True


def test_set_field_sets_its_field_and_holds() -> None:
    cmds, duration = compile_step(make_step("set_field", {"field_ut": [10, -20, 30], "hold_s": 4}))
    assert (cmds, duration) == (
        [
            FieldCommand(0.0, {"field_ut": [10.0, -20.0, 30.0], "trim": False}),
            EndCommand(4.0),
        ],
        4.0,
    )


def test_hold_sets_no_field_and_runs_its_load_profiles_back_to_zero() -> None:
    profile = bind_params(LOAD_PROFILES["constant"], {"current_a": 1.5}, "here", "constant")
    step = make_step(
        "hold", {"hold_s": 5}, loads=("bus",), step_loads={"bus": ("constant", profile)}
    )
    cmds, duration = compile_step(step)
    assert duration == 5.0
    assert not [c for c in cmds if c.kind == "field"]
    assert [(c.t_s, c.payload) for c in cmds if c.kind == "load"] == [
        (0.0, {"channel": "bus", "current_a": 1.5}),
        (5.0, {"channel": "bus", "current_a": 0.0}),
    ]
    assert cmds[-1].kind == "end"


def test_sphere_sweep_spreads_directions_and_magnitudes() -> None:
    step = make_step("sphere_sweep", {"directions": 200, "magnitude_ut": [20, 60], "dwell_s": 0.5})
    cmds, duration = compile_step(step)
    times, fields = fields_of(cmds)
    assert duration == 100.0
    assert times == [0.5 * i for i in range(200)]
    mag = np.linalg.norm(fields, axis=1)
    assert mag.min() == pytest.approx(20.0) and mag.max() == pytest.approx(60.0)
    unit = fields / mag[:, None]
    assert np.linalg.norm(unit.mean(axis=0)) < 0.05  # nearly uniform: no preferred direction
    again, _ = compile_step(
        make_step("sphere_sweep", {"directions": 200, "magnitude_ut": [20, 60]})
    )
    assert fields_of(again)[1] == pytest.approx(fields)  # the same seed, the same order


def test_field_points_holds_each_listed_field_in_turn() -> None:
    listed = [[45.0, 0.0, 0.0], [0.0, -45.0, 0.0], [0.0, 0.0, 30.0]]
    cmds, duration = compile_step(make_step("field_points", {"fields_ut": listed, "dwell_s": 1.5}))
    times, fields = fields_of(cmds)
    assert duration == 4.5 and times == [0.0, 1.5, 3.0]
    assert fields.tolist() == listed and cmds[-1] == EndCommand(4.5)
    for bad, needle in (([], "must be a list of"), ([[1.0, 2.0]], "fields_ut\\[0\\]"),
                        ([[1.0, 2.0, 2000.0]], "within -1000..1000")):  # fmt: skip
        with pytest.raises(ProcedureError, match=needle):
            make_step("field_points", {"fields_ut": bad})


def test_axis_sweep_steps_evenly_along_its_axis() -> None:
    step = make_step(
        "axis_sweep", {"axis": "y", "from_ut": -30, "to_ut": 30, "points": 7, "dwell_s": 1}
    )
    cmds, duration = compile_step(step)
    times, fields = fields_of(cmds)
    assert duration == 7.0 and times == [float(i) for i in range(7)]
    assert fields[:, 1] == pytest.approx(np.linspace(-30, 30, 7))
    assert not fields[:, [0, 2]].any()


def test_rotate_turns_a_constant_magnitude_about_its_axis() -> None:
    axis = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    step = make_step("rotate", {"magnitude_ut": 40, "axis": [1, 1, 0], "points": 12})
    _, fields = fields_of(compile_step(step)[0])
    assert len(fields) == 12
    assert np.linalg.norm(fields, axis=1) == pytest.approx(np.full(12, 40.0))
    assert fields @ axis == pytest.approx(np.zeros(12), abs=1e-9)
    turn = np.degrees(np.arccos(np.clip(fields[0] @ fields[1] / 1600.0, -1, 1)))
    assert turn == pytest.approx(30.0)


def test_orbit_replay_tracks_the_orbit_field_and_drives_the_panels() -> None:
    step = make_step(
        "orbit_replay",
        {
            **ORBIT,
            "duration_s": 20,
            "rate_hz": 2,
            "panels": [{"channel": "bus", "face": "+x", "max_a": 1.0}],
        },
        loads=("bus",),
    )
    cmds, duration = compile_step(step)
    times, fields = fields_of(cmds)
    assert duration == 20.0 and times == [0.5 * i for i in range(40)]
    assert all(c.payload["track"] for c in cmds if c.kind == "field")
    mag = np.linalg.norm(fields, axis=1)
    assert mag.min() > 15.0 and mag.max() < 65.0  # the geomagnetic field in low Earth orbit
    loads = [c.payload["current_a"] for c in cmds if c.kind == "load"]
    assert all(0.0 <= a <= 1.0 for a in loads) and loads[-1] == 0.0


def test_orbit_replay_field_scale_scales_the_field_not_its_direction() -> None:
    """A cage the full orbit field (plus the ambient to cancel) would take to its limits replays
    it scaled: the same directions and panel currents, the magnitude times field_scale."""
    base = {**ORBIT, "duration_s": 10, "rate_hz": 1}
    _, full = fields_of(compile_step(make_step("orbit_replay", base))[0])
    _, half = fields_of(compile_step(make_step("orbit_replay", {**base, "field_scale": 0.6}))[0])
    assert np.asarray(half) == pytest.approx(0.6 * np.asarray(full))


def test_live_calibrate_plans_fields_for_its_longest_time() -> None:
    step = make_step("live_calibrate", {"targets": {"bias_nt": 30}, "max_s": 10, "dwell_s": 0.75})
    cmds, duration = compile_step(step)
    _times, fields = fields_of(cmds)
    assert len(fields) == math.ceil(10 / 0.75) and duration == len(fields) * 0.75
    assert np.linalg.norm(fields, axis=1).min() >= 20.0 - 1e-9


def test_noise_spectrum_nulls_and_holds() -> None:
    cmds, duration = compile_step(make_step("noise_spectrum", {"hold_s": 60}))
    assert duration == 60.0
    assert [(c.t_s, c.kind) for c in cmds] == [(0.0, "field"), (60.0, "end")]


def test_linearity_sweeps_each_axis_to_full_scale_in_turn() -> None:
    step = make_step("linearity", {"points": 5, "dwell_s": 1})
    _, fields = fields_of(compile_step(step)[0])
    assert len(fields) == 15
    for axis in range(3):
        block = fields[5 * axis : 5 * axis + 5]
        assert block[:, axis] == pytest.approx(
            np.linspace(-DEFAULT_FIELD_LIMIT_UT, DEFAULT_FIELD_LIMIT_UT, 5)
        )
        assert not np.delete(block, axis, axis=1).any()
    _, limited = fields_of(compile_step(step, RigTiming(max_field_ut=80.0))[0])
    assert np.abs(limited).max() == 80.0
    _, given = fields_of(compile_step(make_step("linearity", {"max_ut": 30}))[0])
    assert np.abs(given).max() == 30.0


def test_characterize_cage_drives_its_amplitude_for_its_planned_time() -> None:
    step = make_step("characterize_cage", {"amplitude_a": 2, "samples": 5, "repeats": 1})
    kind, timing = KINDS["characterize_cage"], RigTiming()
    assert kind.peak_coil_current_a(step) == 2.0
    assert kind.duration_s(step, timing) == characterization_duration_s(2.0, 5, 1, timing)
    assert kind.duration_s(step, timing) > 14 * (0.2 + 5 / timing.reference_rate_hz)


def test_only_calibrate_names_thermometers() -> None:
    assert KINDS["calibrate"].thermometers(make_step("calibrate", {"temperature": "dut_t"})) == (
        "dut_t",
    )
    assert KINDS["calibrate"].thermometers(make_step("calibrate")) == ()


@pytest.mark.parametrize("rate_hz", [40.0, 47.0, 50.0, 53.0])
def test_a_sines_last_set_point_never_follows_the_next_axiss_bias(rate_hz: float) -> None:
    """Set-points every 1/rate from each sine's start, the last at or before its end: at 47 Hz
    a 4.25 s sine's rounded count put its last set-point 5 ms past the end, after the next
    axis's bias (whose field it put back, by a 0.4 s ramp that slipped the sine)."""
    body = {"frequencies_hz": [0.5, 4], "cycles": 3, "min_s": 4, "rate_hz": rate_hz,
            "amplitude_ut": 10, "bias_ut": 30, "axes": "xyz"}  # fmt: skip
    cmds, _ = compile_step(make_step("frequency_response", body))
    field = [c for c in cmds if c.kind == "field"]
    for before, after in itertools.pairwise(field):
        if "segment" in before.payload and "segment" not in after.payload:  # a bias follows
            assert before.t_s <= after.t_s + 1e-12
    axis_of = [c.payload["segment"][0] if "segment" in c.payload else
               int(np.argmax(c.payload["field_ut"])) for c in field]  # fmt: skip
    # the axes in turn, each once: no axis's set-point after the next one's bias
    changes = [a for a, b in itertools.pairwise(axis_of) if a != b]
    assert changes == [0, 1], changes
