"""Each step kind refuses bad parameters with a message naming the place and the fix, and takes
good ones with its defaults filled in."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from rig.steps.vocabulary import ProcedureError
from tests.steps.fake_context import WHERE, make_step

TLE = [
    "1 25544U 98067A   19343.69339541  .00001764  00000-0  38792-4 0  9991",
    "2 25544  51.6439 211.2001 0007417  17.6667  85.6398 15.50103472202482",
]
ORBIT = {"tle": TLE, "start": "2019-12-09T12:00:00Z", "duration_s": 10}
LIVE = {"targets": {"bias_nt": 30}}

REFUSED: list[tuple[str, dict[str, Any], tuple[str, ...], str]] = [
    ("prompt", {}, (), "prompt needs 'text'"),
    ("null_field", {"hold_s": -1}, (), "'hold_s'"),
    ("null_field", {"trim": "maybe"}, (), "'trim'"),
    ("set_field", {}, (), "set_field needs 'field_ut'"),
    ("set_field", {"field_ut": [1, 2]}, (), "'field_ut'"),
    ("hold", {}, (), "hold needs 'hold_s'"),
    ("hold", {"hold_s": 5, "dwell_s": 1}, (), "hold has no parameter 'dwell_s'"),
    ("sphere_sweep", {"directions": 3}, (), "'directions'"),
    ("sphere_sweep", {"dwell_s": 0.01}, (), "'dwell_s'"),
    ("axis_sweep", {"axis": "w"}, (), "'axis'"),
    ("axis_sweep", {"points": 1}, (), "'points'"),
    ("rotate", {"axis": [0, 0, 0]}, (), "axis must not be zero"),
    ("rotate", {"points": 2}, (), "'points'"),
    ("orbit_replay", {**ORBIT, "tle": TLE[:1]}, (), "'tle' must be the two TLE lines"),
    ("orbit_replay", {**ORBIT, "start": "noon"}, (), "not an ISO date-time"),
    ("orbit_replay", {**ORBIT, "duration_s": 86400, "rate_hz": 200}, (), "MAX_FIELD_SETPOINTS"),
    (
        "orbit_replay",
        {**ORBIT, "panels": [{"channel": "bus", "face": "+x", "max_a": 1}]},
        (),
        "a panel needs channel",
    ),
    (
        "orbit_replay",
        {**ORBIT, "panels": [{"channel": "bus", "face": "up", "max_a": 1}]},
        ("bus",),
        "a panel needs channel",
    ),
    ("live_calibrate", {**LIVE, "telemetry": ["bsu"]}, ("bus",), "did you mean 'bus'"),
    ("live_calibrate", {"targets": {"bias": 30}}, (), "unknown target 'bias'"),
    ("live_calibrate", {"targets": {"scale": 0}}, (), "must be a positive 1-sigma"),
    ("live_calibrate", {"targets": {"scale": True}}, (), "must be a positive 1-sigma"),
    ("live_calibrate", {"targets": {"k_ut_per_a": 0.1}}, (), "needs 'telemetry'"),
    ("live_calibrate", {}, (), "stop_on_target needs 'targets'"),
    ("live_calibrate", {**LIVE, "min_s": 70, "max_s": 60}, (), "min_s must not exceed max_s"),
    ("live_calibrate", {**LIVE, "max_s": 86400, "dwell_s": 0.05}, (), "lengthen dwell_s"),
    ("live_calibrate", {**LIVE, "method": "lsq"}, (), "'method'"),
    ("noise_spectrum", {"band_hz": [2, 2]}, (), "low < high"),
    ("noise_spectrum", {"hold_s": 10, "band_hz": [0.1, 5]}, (), "4 periods"),
    ("noise_spectrum", {"hold_s": 1}, (), "'hold_s'"),
    ("linearity", {"points": 4}, (), "'points'"),
    ("linearity", {"max_ut": 2000}, (), "'max_ut'"),
    ("characterize_cage", {"amplitude_a": 0}, (), "'amplitude_a'"),
    ("characterize_cage", {"repeats": 21}, (), "'repeats'"),
    ("calibrate", {"model": "tensor"}, (), "'model'"),
    ("calibrate", {"method": "guess"}, (), "'method'"),
    ("calibrate", {"settle_s": -1}, (), "'settle_s'"),
    ("check", {}, (), "check needs 'criteria'"),
    ("check", {"criteria": [{"result": "a", "value": "b"}]}, (), "needs result, value and min"),
    (
        "check",
        {"criteria": [{"result": "a", "value": "b", "max": 1, "unit": "nT"}]},
        (),
        "unknown ['unit']",
    ),
    (
        "check",
        {"criteria": [{"result": "a", "value": "b", "max": "lots"}]},
        (),
        "'max' must be a number",
    ),
    (
        "check",
        {"criteria": [{"result": "a", "value": "b", "min": float("nan")}]},
        (),
        "'min' must be a finite number",
    ),
    ("report", {"format": "pdf"}, (), "report has no parameter 'format'"),
]


@pytest.mark.parametrize(
    ("kind", "body", "loads", "says"), REFUSED, ids=[f"{r[0]}-{r[3][:30]}" for r in REFUSED]
)
def test_bad_parameters_are_refused_with_a_clear_message(
    kind: str, body: dict[str, Any], loads: tuple[str, ...], says: str
) -> None:
    with pytest.raises(ProcedureError) as err:
        make_step(kind, body, loads=loads)
    message = str(err.value)
    assert message.startswith(WHERE), message
    assert says in message, message


def test_defaults_are_filled_in() -> None:
    step = make_step("sphere_sweep")
    assert step.params == {
        "directions": 40,
        "magnitude_ut": [30.0, 30.0],
        "dwell_s": 0.5,
        "seed": 1,
    }
    assert make_step("prompt", "Mount the DUT").params == {"text": "Mount the DUT"}


def test_check_converts_limits_given_as_text() -> None:
    step = make_step("check", {"criteria": [{"result": "a", "value": "b", "min": "1.5"}]})
    assert step.params["criteria"][0]["min"] == 1.5


def test_live_calibrate_targets_become_floats() -> None:
    step = make_step("live_calibrate", {"targets": {"bias_nt": 30}})
    assert step.params["targets"] == {"bias_nt": 30.0}
    assert isinstance(step.params["targets"]["bias_nt"], float)


def test_cross_field_sweeps_every_pair_and_refuses_too_few_levels() -> None:
    from rig.steps import KINDS
    from rig.steps.vocabulary import RigTiming

    step = make_step("cross_field", {"levels_ut": [-20, 0, 20], "dwell_s": 0.5})
    fields = KINDS["cross_field"].fields(step, RigTiming())
    assert len(fields) == 6 * 3 * 3 and fields[-1][0] == pytest.approx(53 * 0.5)
    assert {tuple(np.flatnonzero(f)) for _, f in fields} >= {(0, 1), (0, 2), (1, 2)}
    with pytest.raises(ProcedureError, match="at least 3 different levels"):
        make_step("cross_field", {"levels_ut": [10, 10, 20]})
    with pytest.raises(ProcedureError, match="settle_s must be shorter than dwell_s"):
        make_step("cross_field", {"dwell_s": 0.2, "settle_s": 0.3})
