"""The procedure language: YAML with a closed vocabulary, validated with file:line errors.

    procedure: DUT acceptance
    parameters:
      dut_serial: {default: SN-0001, description: serial number on the DUT label}
      note: {default: "", allow_empty: yes}   # --set note= is refused unless allow_empty
    magnetometers: {dut: dut, reference: reference}   # roles -> rig device names
    loads: [load_bus, load_panel]
    steps:
      - prompt: "Mount DUT {dut_serial} and close the cage door"
      - null_field: {hold_s: 5, name: noise floor}
      - sphere_sweep: {directions: 40, magnitude_ut: [20, 60], dwell_s: 0.6}
        loads:
          load_bus: {steps: {levels_a: [0, 0.6], dwell_s: 3}}
      - calibrate: {name: vector, model: vector, telemetry: [load_bus]}
      - check: {criteria: [{result: vector, value: residual_rms_nt, max: 100}]}

Strings may use ``{parameter}``; nothing is evaluated. Every error names the file, the line, the
step and the fix.
"""

from __future__ import annotations

import difflib
import string
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rig.errors import UserInputError


class ProcedureError(UserInputError):
    """A procedure file is malformed."""


@dataclass(frozen=True)
class Where:
    """A place in a procedure file."""

    path: str
    line: int

    def __str__(self) -> str:
        return f"{self.path}:{self.line}"


class _LineLoader(yaml.SafeLoader):
    """safe_load that records each mapping's line number under ``__line__``."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        mapping: dict[Any, Any] = dict(super().construct_mapping(node, deep=deep))
        mapping["__line__"] = node.start_mark.line + 1
        return mapping


def load_yaml(path: Path) -> dict[str, Any]:
    """Parse with line numbers; YAML syntax errors cite the line."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ProcedureError(f"{path}: no such procedure; see the procedures/ folder") from None
    try:
        data = yaml.load(text, Loader=_LineLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ProcedureError(
            f"{path}{line}: YAML syntax: {problem}; check indentation and quoting"
        ) from None
    if not isinstance(data, dict):
        raise ProcedureError(f"{path}:1: a procedure is a mapping with 'procedure' and 'steps'")
    return data


# --- the vocabulary -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Param:
    """One named parameter of a step: type, default (None = required), bounds."""

    kind: str  # "float", "int", "str", "vec3", "range2", "list_str", "list_float", "dict", "list_dict"
    default: Any = None
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[str, ...] = ()
    required: bool = False


FIELD_STEPS: dict[str, dict[str, Param]] = {
    "null_field": {
        "hold_s": Param("float", 2.0, 0.0, 86400.0),
        "trim": Param("str", "no", choices=("yes", "no")),
    },
    "set_field": {
        "field_ut": Param("vec3", required=True),
        "hold_s": Param("float", 2.0, 0.0, 86400.0),
        "trim": Param("str", "no", choices=("yes", "no")),
    },
    "hold": {"hold_s": Param("float", required=True, minimum=0.0, maximum=86400.0)},
    "sphere_sweep": {
        "directions": Param("int", 40, 4, 10000),
        "magnitude_ut": Param("range2", [30.0, 30.0], 0.0, 1000.0),
        "dwell_s": Param("float", 0.5, 0.05, 3600.0),
        "seed": Param("int", 1, 0, 2**31),
    },
    "axis_sweep": {
        "axis": Param("str", "x", choices=("x", "y", "z")),
        "from_ut": Param("float", -50.0),
        "to_ut": Param("float", 50.0),
        "points": Param("int", 11, 2, 10000),
        "dwell_s": Param("float", 0.5, 0.05, 3600.0),
    },
    "orbit_replay": {
        "tle": Param("list_str", required=True),
        "start": Param("str", required=True),
        "duration_s": Param("float", required=True, minimum=0.1, maximum=86400.0),
        "time_scale": Param("float", 1.0, 0.01, 10000.0),
        "rate_hz": Param("float", 10.0, 0.1, 200.0),
        "attitude": Param("str", "nadir", choices=("inertial", "nadir", "tumbling")),
        "tumble_deg_s": Param("float", 2.0, 0.0, 360.0),
        "panels": Param("list_dict", []),
    },
    "live_calibrate": {
        "method": Param("str", "ukf", choices=("centered-seq", "ekf", "ukf")),
        "telemetry": Param("list_str", []),
        "targets": Param("dict", {}),
        "stop_on_target": Param("str", "yes", choices=("yes", "no")),
        "min_s": Param("float", 5.0, 0.0, 86400.0),
        "max_s": Param("float", 60.0, 1.0, 86400.0),
        "magnitude_ut": Param("range2", [20.0, 50.0], 0.0, 1000.0),
        "dwell_s": Param("float", 0.8, 0.05, 3600.0),
        "seed": Param("int", 1, 0, 2**31),
        "noise_nt": Param("float", 0.0, 0.0, 1e6),
        "settle_s": Param("float", 0.25, 0.0, 60.0),
        "magnetometer": Param("str", "dut"),
    },
    "rotate": {
        "magnitude_ut": Param("float", 40.0, 0.0, 1000.0),
        "axis": Param("vec3", [0.0, 0.0, 1.0]),
        "points": Param("int", 36, 3, 10000),
        "dwell_s": Param("float", 0.3, 0.02, 3600.0),
    },
}
OTHER_STEPS: dict[str, dict[str, Param]] = {
    "prompt": {"text": Param("str", required=True)},
    "calibrate": {
        "model": Param("str", "vector", choices=("vector", "scalar")),
        "method": Param(
            "str", "", choices=("", "ml", "twostep", "centered", "ellipsoid", "vector")
        ),
        "magnetometer": Param("str", "dut"),
        "telemetry": Param("list_str", []),
        "steps": Param("list_str", []),
        "noise_nt": Param("float", 0.0, 0.0, 1e6),
        "settle_s": Param("float", 0.25, 0.0, 60.0),
    },
    "check": {"criteria": Param("list_dict", required=True)},
    "characterize_cage": {
        "amplitude_a": Param("float", 1.0, 0.01, 100.0),
        "samples": Param("int", 10, 1, 10000),
        "repeats": Param("int", 2, 1, 20),
    },
    "report": {},
}
STEP_KINDS = {**FIELD_STEPS, **OTHER_STEPS}
COMMON_KEYS = {"name", "loads"}
LOAD_PROFILES: dict[str, dict[str, Param]] = {
    "constant": {"current_a": Param("float", required=True, minimum=-1000.0, maximum=1000.0)},
    "steps": {
        "levels_a": Param("list_float", required=True),
        "dwell_s": Param("float", required=True, minimum=0.05),
    },
    "square": {
        "low_a": Param("float", 0.0),
        "high_a": Param("float", required=True),
        "period_s": Param("float", required=True, minimum=0.1),
        "duty": Param("float", 0.5, 0.01, 0.99),
    },
    "ramp": {
        "from_a": Param("float", 0.0),
        "to_a": Param("float", required=True),
        "step_s": Param("float", 0.1, 0.02),
    },
    "beacon": {
        "base_a": Param("float", 0.0),
        "pulse_a": Param("float", required=True),
        "period_s": Param("float", 20.0, 0.1),
        "width_s": Param("float", 2.0, 0.01),
    },
    "csv": {"file": Param("str", required=True), "column": Param("str", required=True)},
}
CRITERION_KEYS = {"result", "value", "min", "max", "name", "__line__"}


@dataclass(frozen=True)
class Step:
    """A validated step."""

    index: int
    kind: str
    name: str
    params: dict[str, Any]
    loads: dict[str, tuple[str, dict[str, Any]]]
    where: Where
    loads_allowed: tuple[str, ...] = ()


@dataclass(frozen=True)
class Procedure:
    """A validated procedure with its parameters bound."""

    title: str
    path: Path
    parameters: dict[str, str]
    magnetometers: dict[str, str]
    loads: tuple[str, ...]
    steps: tuple[Step, ...]
    text: str = field(default="", repr=False)


def _suggest(word: object, options: list[str] | set[str] | dict[str, Any]) -> str:
    # YAML keys need not be text ("? " makes a null key, "1:" a number)
    close = difflib.get_close_matches(str(word), [str(o) for o in options], n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _coerce(value: Any, p: Param, key: str, where: str) -> Any:
    def bad(what: str) -> ProcedureError:
        return ProcedureError(f"{where}: '{key}' {what}")

    if p.kind in ("float", "int"):
        if isinstance(value, str):  # a "{parameter}" substituted from --set or a default
            try:
                value = float(value)
            except ValueError:
                raise bad(f"must be a number, got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad(f"must be a number, got {value!r}")
        if p.kind == "int" and not float(value).is_integer():
            raise bad(f"must be a whole number, got {value!r}")
        v = int(value) if p.kind == "int" else float(value)
        if (p.minimum is not None and v < p.minimum) or (p.maximum is not None and v > p.maximum):
            raise bad(f"must be within {p.minimum:g}..{p.maximum:g}, got {v:g}")
        return v
    if p.kind == "str":
        if isinstance(value, bool):
            value = "yes" if value else "no"
        if not isinstance(value, str | int | float):
            raise bad(f"must be text, got {value!r}")
        value = str(value)
        if p.choices and value not in p.choices:
            options = ", ".join(c or "''" for c in p.choices)
            raise bad(f"must be one of {options}, got {value!r}{_suggest(value, set(p.choices))}")
        return value
    if p.kind in ("vec3", "range2", "list_float"):
        n = {"vec3": 3, "range2": 2}.get(p.kind)
        if (
            not isinstance(value, list)
            or (n is not None and len(value) != n)
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        ):
            raise bad(f"must be a list of {n or 'some'} numbers, got {value!r}")
        vals = [float(v) for v in value]
        if p.kind == "range2":
            if vals[0] > vals[1]:
                raise bad(f"must be [low, high], got {value!r}")
            if (p.minimum is not None and vals[0] < p.minimum) or (
                p.maximum is not None and vals[1] > p.maximum
            ):
                raise bad(f"must be within {p.minimum:g}..{p.maximum:g}")
        if p.kind == "list_float" and not vals:
            raise bad("must not be empty")
        return vals
    if p.kind == "list_str":
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise bad(f"must be a list of names, got {value!r}")
        return list(value)
    if p.kind == "dict":
        if not isinstance(value, dict):
            raise bad(f"must be a mapping of name: value, got {value!r}")
        return {k: v for k, v in value.items() if k != "__line__"}
    if p.kind == "list_dict":
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise bad("must be a list of mappings")
        return value
    raise AssertionError(p.kind)


def _params(spec: dict[str, Param], given: dict[str, Any], where: str, what: str) -> dict[str, Any]:
    out = {}
    for key in given:
        if key == "__line__":
            continue
        if key not in spec:
            raise ProcedureError(
                f"{where}: {what} has no parameter '{key}'{_suggest(key, spec)}; allowed: {', '.join(spec) or 'none'}"
            )
    for key, p in spec.items():
        if key in given:
            out[key] = _coerce(given[key], p, key, where)
        elif p.required:
            raise ProcedureError(f"{where}: {what} needs '{key}'")
        else:
            out[key] = p.default
    return out


class _Strict(string.Formatter):
    def __init__(self, names: dict[str, str], where: str) -> None:
        self.names, self.where = names, where

    def get_value(self, key: Any, args: Any, kwargs: Any) -> Any:
        if key not in self.names:
            raise ProcedureError(
                f"{self.where}: unknown parameter '{{{key}}}'{_suggest(str(key), self.names)}; declare it under 'parameters'"
            )
        return self.names[key]


def _substitute(value: Any, names: dict[str, str], where: str) -> Any:
    if isinstance(value, str):
        try:
            return _Strict(names, where).format(value)
        except (ValueError, IndexError) as exc:
            raise ProcedureError(
                f"{where}: bad placeholder in {value!r} ({exc}); use {{name}} or double braces"
            ) from None
    if isinstance(value, list):
        return [_substitute(v, names, where) for v in value]
    if isinstance(value, dict):
        return {k: _substitute(v, names, where) for k, v in value.items()}
    return value


def _check_live(params: dict[str, Any], loads: list[str], where: str) -> None:
    """``live_calibrate``: telemetry among the loads, targets known and positive."""
    from rig.calibration.targets import SIGMA_TARGETS

    for ch in params["telemetry"]:
        if ch not in loads:
            raise ProcedureError(
                f"{where}: telemetry '{ch}' is not in the procedure's 'loads' list{_suggest(ch, loads)}"
            )
    targets = params["targets"]
    for key, value in targets.items():
        if key not in SIGMA_TARGETS:
            raise ProcedureError(
                f"{where}: unknown target '{key}'{_suggest(key, SIGMA_TARGETS)}; targets are: {', '.join(SIGMA_TARGETS)}"
            )
        if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
            raise ProcedureError(
                f"{where}: target '{key}' must be a positive 1-sigma, got {value!r}"
            )
        targets[key] = float(value)
    if "k_ut_per_a" in targets and not params["telemetry"]:
        raise ProcedureError(f"{where}: target 'k_ut_per_a' needs 'telemetry' channels")
    if params["stop_on_target"] == "yes" and not targets:
        raise ProcedureError(
            f"{where}: stop_on_target needs 'targets', e.g. {{bias_nt: 30, scale: 0.002}}; or set stop_on_target: no"
        )
    if params["min_s"] > params["max_s"]:
        raise ProcedureError(f"{where}: min_s must not exceed max_s")


def parse_procedure(path: str | Path, overrides: dict[str, str] | None = None) -> Procedure:
    """Read, validate and bind a procedure. ``overrides`` set parameters (``--set name=value``)."""
    path = Path(path)
    data = load_yaml(path)
    top = Where(str(path), data.get("__line__", 1))
    allowed = {
        "procedure",
        "parameters",
        "magnetometers",
        "loads",
        "steps",
        "__line__",
        "description",
    }
    for key in data:
        if key not in allowed:
            raise ProcedureError(f"{top}: unknown top-level key '{key}'{_suggest(key, allowed)}")
    if not isinstance(data.get("procedure"), str):
        raise ProcedureError(f"{top}: needs 'procedure: <title>'")
    declared = data.get("parameters") or {}
    if not isinstance(declared, dict):
        raise ProcedureError(f"{top}: 'parameters' must be a mapping of name: {{default: ...}}")
    names: dict[str, str] = {}
    may_be_empty: set[str] = set()
    for name, spec in declared.items():
        if name == "__line__":
            continue
        default = spec.get("default") if isinstance(spec, dict) else spec
        names[name] = "" if default is None else str(default)
        if isinstance(spec, dict) and spec.get("allow_empty") in (True, "yes"):
            may_be_empty.add(name)
    for name, value in (overrides or {}).items():
        if name not in names:
            raise ProcedureError(
                f"{path}: --set {name}=...: the procedure has no parameter '{name}'{_suggest(name, names)}"
            )
        if not value.strip() and name not in may_be_empty:
            default = (
                f", or leave out --set {name} to use the default {names[name]!r}"
                if names[name]
                else ""
            )
            raise ProcedureError(
                f"{path}: --set {name}= is empty: give a value, e.g. --set {name}=VALUE{default}"
            )
        names[name] = value
    mags = data.get("magnetometers") or {"dut": "dut", "reference": "reference"}
    if not isinstance(mags, dict) or "dut" not in mags:
        raise ProcedureError(f"{top}: 'magnetometers' must map roles to devices and include 'dut'")
    mags = {k: str(v) for k, v in mags.items() if k != "__line__"}
    loads = data.get("loads") or []
    if not isinstance(loads, list) or not all(isinstance(x, str) for x in loads):
        raise ProcedureError(f"{top}: 'loads' must be a list of load-channel device names")
    raw_steps = data.get("steps")
    if not isinstance(raw_steps, list) or not raw_steps:
        raise ProcedureError(f"{top}: needs a non-empty 'steps' list")
    steps = []
    for i, raw in enumerate(raw_steps):
        line = raw.get("__line__", top.line) if isinstance(raw, dict) else top.line
        where = f"{path}:{line}: step {i + 1}"
        if not isinstance(raw, dict):
            raise ProcedureError(f"{where}: a step is a mapping like '- hold: {{hold_s: 5}}'")
        kinds = [k for k in raw if k in STEP_KINDS]
        unknown = [
            k for k in raw if k not in STEP_KINDS and k not in COMMON_KEYS and k != "__line__"
        ]
        if unknown:
            raise ProcedureError(
                f"{where}: unknown step or key '{unknown[0]}'{_suggest(unknown[0], list(STEP_KINDS) + list(COMMON_KEYS))}; steps are: {', '.join(STEP_KINDS)}"
            )
        if len(kinds) != 1:
            raise ProcedureError(
                f"{where}: exactly one step kind per list item, found {kinds or 'none'}"
            )
        kind = kinds[0]
        body = raw[kind]
        if kind == "prompt" and isinstance(body, str):
            body = {"text": body}
        if body is None:
            body = {}
        if not isinstance(body, dict):
            raise ProcedureError(
                f"{where} ({kind}): parameters must be a mapping, e.g. '{kind}: {{...}}'"
            )
        body = _substitute(body, names, where)
        params = _params(STEP_KINDS[kind], body, f"{where} ({kind})", kind)
        step_loads: dict[str, tuple[str, dict[str, Any]]] = {}
        for ch, prof in (raw.get("loads") or {}).items():
            if ch == "__line__":
                continue
            if ch not in loads:
                raise ProcedureError(
                    f"{where}: load '{ch}' is not in the procedure's 'loads' list{_suggest(ch, loads)}"
                )
            if kind not in FIELD_STEPS:
                raise ProcedureError(
                    f"{where}: load profiles run during field steps, not during '{kind}'"
                )
            if not isinstance(prof, dict) or len([k for k in prof if k != "__line__"]) != 1:
                raise ProcedureError(
                    f"{where}: load '{ch}' needs exactly one profile: {', '.join(LOAD_PROFILES)}"
                )
            pkind = next(k for k in prof if k != "__line__")
            if pkind not in LOAD_PROFILES:
                raise ProcedureError(
                    f"{where}: load '{ch}': unknown profile '{pkind}'{_suggest(pkind, LOAD_PROFILES)}"
                )
            step_loads[ch] = (
                pkind,
                _params(LOAD_PROFILES[pkind], prof[pkind] or {}, f"{where} load '{ch}'", pkind),
            )
        if kind == "check":
            for c in params["criteria"]:
                bad = set(c) - CRITERION_KEYS
                if (
                    bad
                    or "result" not in c
                    or "value" not in c
                    or ("min" not in c and "max" not in c)
                ):
                    raise ProcedureError(
                        f"{path}:{c.get('__line__', line)}: step {i + 1} (check): a criterion needs result, value and min and/or max{f'; unknown {sorted(bad)}' if bad else ''}"
                    )
        if kind == "live_calibrate":
            _check_live(params, loads, f"{where} (live_calibrate)")
        name = str(raw.get("name") or params.get("name") or f"{kind} {i + 1}")
        steps.append(
            Step(
                i,
                kind,
                _substitute(name, names, where),
                params,
                step_loads,
                Where(str(path), line),
                tuple(loads),
            )
        )
    return Procedure(
        str(data["procedure"]),
        path,
        names,
        mags,
        tuple(loads),
        tuple(steps),
        path.read_text(encoding="utf-8"),
    )
