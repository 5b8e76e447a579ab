"""Hostile input for every parser: never an unhandled exception, always the module's clear error.

HMR2300 binary and ASCII frames and its stream resynchronisation (over a simulated serial line),
ASCII-line sensor lines, procedure YAML and rig configuration TOML. The CSV reader has its own
property tests in test_csv_table.py.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from drivers.errors import DeviceProtocolError
from drivers.mag.ascii_line import LineFormat
from drivers.mag.hmr2300 import ASCII_LEN, BINARY_LEN, Hmr2300, parse_ascii, parse_binary
from rig.config import load_rig_config
from rig.errors import UserInputError
from rig.procedure.language import ProcedureError, parse_procedure
from sim.hmr2300 import ascii_frame

FUZZ = settings(max_examples=300, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
HMR_MAX_UT = 32768 / 150.0


def _finite_triple(v: tuple[float, float, float], limit: float = math.inf) -> bool:
    return len(v) == 3 and all(math.isfinite(x) and abs(x) <= limit for x in v)


@FUZZ
@given(st.binary(max_size=40))
def test_hmr2300_frames_parse_or_fail_clearly(data: bytes) -> None:
    for parse in (parse_binary, parse_ascii):
        try:
            assert _finite_triple(parse(data), HMR_MAX_UT)
        except DeviceProtocolError as exc:
            assert str(exc).startswith("HMR2300:")


@FUZZ
@given(st.tuples(*[st.integers(-32768, 32767)] * 3))
def test_hmr2300_frames_round_trip(counts: tuple[int, int, int]) -> None:
    """The driver reads what the simulator's independent encoder writes."""
    want = tuple(c / 150.0 for c in counts)
    assert parse_binary(_frame(counts)) == want
    frame = ascii_frame(counts)
    assert len(frame) == ASCII_LEN and parse_ascii(frame) == pytest.approx(want, abs=1e-12)


def _frame(counts: tuple[int, int, int]) -> bytes:
    return struct.pack(">hhh", *counts) + b"\r"


no_cr = st.integers(-32768, 32767).filter(lambda c: 0x0D not in struct.pack(">h", c))


@FUZZ
@given(
    garbage=st.binary(max_size=30).map(lambda b: b.replace(b"\r", b"")),
    frames=st.lists(st.tuples(no_cr, no_cr, no_cr), min_size=3, max_size=8),
    tail=st.binary(max_size=BINARY_LEN - 1),
    pieces=st.integers(1, 5),
)
def test_hmr2300_stream_resyncs_after_garbage_and_partial_frames(
    garbage: bytes, frames: list[tuple[int, int, int]], tail: bytes, pieces: int
) -> None:
    """Garbage, then whole frames, then a partial frame, through a serial line in simulated time
    (its 50 ms read timeouts cost no wall time), arriving in ``pieces`` writes 10 ms apart."""
    import timebase
    from timebase.wires import wires

    data = garbage + b"".join(_frame(f) for f in frames) + tail
    with timebase.simulated(stall_report_s=None):
        line = wires().serve_serial("hmr2300", baud=None)
        dev = Hmr2300(line.url, device_id=0, timeout_s=0.05, set_reset_auto=False)

        def sensor() -> None:
            size = -(-len(data) // pieces)
            for start in range(0, len(data), size):
                line.device.write(data[start : start + size])
                timebase.sleep(0.01)

        try:
            dev.binary = True
            timebase.Thread(sensor, name="sensor").start()
            # everything the line delivers, in as many reads as it takes (a busy computer's
            # reader sees the bytes in pieces): frames split across reads must be recovered too
            got: list[tuple[float, float, float]] = []
            while chunk := dev.read_stream(0.05):
                got += chunk
        finally:
            dev.close()
    want = [tuple(c / 150.0 for c in f) for f in frames]
    assert all(_finite_triple(v, HMR_MAX_UT) for v in got)
    # every frame after the garbage is recovered, at most the first one lost to the resync
    assert got[-(len(frames) - 1) :] == want[1:], (got, want)


line_bytes = st.one_of(
    st.binary(max_size=60),
    st.lists(
        st.one_of(
            st.floats(allow_nan=True, allow_infinity=True).map(repr),
            st.sampled_from(["nan", "inf", "-inf", "1e999", "", "x", "1,2", "+-1", "0x10"]),
        ),
        max_size=5,
    ).map(lambda cells: " ".join(cells).encode()),
)


@FUZZ
@given(line=line_bytes, delimiter=st.sampled_from([None, ",", ";"]))
def test_ascii_line_parses_finite_values_or_fails_clearly(
    line: bytes, delimiter: str | None
) -> None:
    fmt = LineFormat(delimiter=delimiter, scale_to_ut=0.001)
    try:
        assert _finite_triple(fmt.parse(line))
    except DeviceProtocolError as exc:
        assert "magnetometer line" in str(exc)


# --- files ----------------------------------------------------------------------------------------

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
    st.text(max_size=12),
)  # fmt: skip
yaml_values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.dictionaries(
            st.sampled_from(
                [
                    "hold_s",
                    "field_ut",
                    "steps",
                    "name",
                    "loads",
                    "criteria",
                    "directions",
                    "targets",
                    "bias_nt",
                    "telemetry",
                    "x",
                ]
            )
            | st.text(max_size=6),
            inner,
            max_size=4,
        ),
    ),
    max_leaves=12,
)
step_kinds = st.sampled_from(["hold", "null_field", "set_field", "sphere_sweep", "axis_sweep",
                              "rotate", "orbit_replay", "live_calibrate", "calibrate", "check",
                              "prompt", "characterize_cage", "report", "nope"])  # fmt: skip


def _procedure(steps: list[Any], extra: dict[str, Any]) -> dict[str, Any]:
    return {"procedure": "fuzz", "loads": ["bus"], "steps": steps} | extra


@FUZZ
@given(
    steps=st.lists(st.dictionaries(step_kinds, yaml_values, min_size=1, max_size=2), max_size=4),
    extra=st.dictionaries(
        st.sampled_from(["parameters", "magnetometers", "loads", "junk"]), yaml_values, max_size=2
    ),
)
@example(steps=[{"hold": {"\n": None}}], extra={})  # a key with a line break: still one line
def test_procedure_files_load_or_fail_with_a_clear_error(
    tmp_path: Path, steps: list[Any], extra: dict[str, Any]
) -> None:
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(_procedure(steps, extra), allow_unicode=True))
    try:
        proc = parse_procedure(path)
        assert proc.steps
    except ProcedureError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc)


@FUZZ
@given(st.text(max_size=200))
@example("?")  # a null key (once a TypeError in the spelling suggestion)
def test_procedure_text_of_any_kind_fails_clearly(tmp_path: Path, text: str) -> None:
    path = tmp_path / "p.yaml"
    path.write_text(text, encoding="utf-8")
    try:
        parse_procedure(path)
    except ProcedureError as exc:
        assert str(exc).startswith(str(path))


toml_values = st.one_of(
    st.integers(-5, 70000).map(str), st.sampled_from(['"modbus-tcp"', '"modbus-rtu"', '"serial"',
    '"i2c"', '"riden-rd60xx"', '"hmr2300"', '"rm3100"', '"x"', "[1, 2]", "[]", "true", "-1.5",
    '"127.0.0.1"', '"/dev/null"', "{}", '["coil_x", "coil_y", "coil_z"]']),
)  # fmt: skip
toml_keys = st.sampled_from(["kind", "protocol", "host", "port", "path", "baudrate", "device_id",
                             "address", "bus", "regmap", "max_current_a", "axes", "reference",
                             "max_field_ut", "slew_ut_per_s", "polarity", "relay", "junk"])  # fmt: skip


@FUZZ
@given(
    devices=st.dictionaries(st.sampled_from(["coil_x", "coil_y", "coil_z", "dut", "relay", "a b"]),
                            st.dictionaries(toml_keys, toml_values, max_size=6), max_size=4),
    cage=st.none() | st.dictionaries(toml_keys, toml_values, max_size=6),
    noise=st.text(max_size=20),
)  # fmt: skip
def test_rig_configuration_loads_or_fails_with_a_clear_error(
    tmp_path: Path, devices: dict[str, dict[str, str]], cage: dict[str, str] | None, noise: str
) -> None:
    lines = []
    for name, spec in devices.items():
        lines.append(f'[devices."{name}"]')
        lines += [f"{k} = {v}" for k, v in spec.items()]
    if cage is not None:
        lines.append("[cage]")
        lines += [f"{k} = {v}" for k, v in cage.items()]
    path = tmp_path / "rig.toml"
    path.write_text("\n".join(lines) + "\n" + noise, encoding="utf-8")
    try:
        load_rig_config(path)
    except UserInputError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc)
