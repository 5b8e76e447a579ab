"""The procedure vocabulary's data: where a thing is in a file, step parameters and their checks,
a validated step and procedure, and the commands a step compiles to.

Below both the language (which parses files into these) and the step kinds (which declare their
parameters with :class:`StepParam` and compile to :class:`Command` lists).
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Required, TypedDict

from rig.errors import UserInputError

# --- limits: what a procedure may ask for (docs/procedures.md, "Limits") ----------------------------
# Each is checked before the work it bounds, and its error names the file, the line and the limit.

MAX_PROCEDURE_FILE_BYTES = 1024 * 1024
"""Largest procedure file (bytes; 1 MiB). The shipped procedures are under 3 KiB; a larger file is
refused before it is parsed."""
MAX_YAML_DEPTH = 32
"""Deepest nesting of mappings and lists in a procedure file (levels; the language uses 8)."""
MAX_YAML_ALIASES = 100
"""YAML aliases (``*name``) a procedure file may use."""
MAX_YAML_NODES = 500_000
"""Values (scalars, lists and mappings) a procedure file may hold, counted with every alias
expanded: a YAML alias bomb ("billion laughs") is refused while it is being read."""
MAX_STEPS = 10_000
"""Steps in one procedure; the file is refused as soon as its step list grows past it."""
MAX_TOTAL_DURATION_S = 7 * 86400.0
"""Longest procedure (s; 7 days), its steps' nominal durations summed (ramps left out)."""
MAX_LOAD_SETPOINTS_PER_STEP = 1_000_000
"""Load-current set-points the load profiles of one step may make, all channels together."""
MAX_FIELD_SETPOINTS_PER_STEP = 1_000_000
"""Field set-points one step may make (an orbit replay's duration x rate, a live calibration's
max_s / dwell_s): a day at 10 Hz, 1.4 h at the 200 Hz maximum rate."""
MAX_CSV_PROFILE_BYTES = 1024 * 1024
"""Largest CSV load profile file (bytes; 1 MiB)."""
MAX_CSV_PROFILE_ROWS = 100_000
"""Data rows of a CSV load profile."""


class ProcedureError(UserInputError):
    """A procedure file is malformed."""


class NotFiniteError(ProcedureError):
    """A number in a procedure is nan, infinite, or too large to be a number (beyond 1.8e308)."""


NOT_FINITE_FIX = (
    "nan, inf and numbers beyond 1.8e308 are refused anywhere in a procedure: write a finite number"
)


def finite_number(value: int | float) -> float | None:
    """``value`` as a float, None if it is nan, infinite or too large for a float."""
    try:
        v = float(value)
    except OverflowError:  # an int beyond 1.8e308
        return None
    return v if math.isfinite(v) else None


def inside_folder(folder: Path, name: str) -> Path:
    """The file ``name`` (relative to ``folder`` or absolute) that a procedure in ``folder`` names,
    resolved (links and ``..`` followed); a :class:`ProcedureError` unless it lies inside
    ``folder`` (itself resolved)."""
    root = folder.resolve()
    try:
        target = (root / name).resolve()
    except (OSError, RuntimeError, ValueError) as exc:  # a link loop, a NUL byte
        raise ProcedureError(f"file {name!r}: cannot be resolved ({exc})") from None
    if not target.is_relative_to(root):
        raise ProcedureError(
            f"file {name!r} resolves to {target}, outside {root}: files a procedure names must be"
            " in the procedure's folder (links and '..' are followed); copy the file there"
        )
    return target


@dataclass(frozen=True)
class Where:
    """A place in a procedure file."""

    path: str
    line: int

    def __str__(self) -> str:
        return f"{self.path}:{self.line}"


@dataclass(frozen=True)
class StepParam:
    """One named parameter of a step: type, default (None = required), bounds."""

    kind: str  # "float", "int", "str", "vec3", "range2", "list_str", "list_float", "list_vec3", "dict", "list_dict"
    default: Any = None
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[str, ...] = ()
    required: bool = False
    text: Literal["label", "free", "path"] = "label"
    """What its strings are (rig.text): a label (at most MAX_TEXT_CHARS characters), free text
    (tab and line feed allowed, no length limit) or a file name (no length limit)."""


@dataclass(frozen=True)
class Step:
    """A validated step."""

    index: int
    kind: str
    name: str
    params: dict[str, Any]
    loads: dict[str, tuple[str, dict[str, Any]]]
    where: Where


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


class FieldPayload(TypedDict, total=False):
    """A field set-point's payload: ``field_ut`` (uT, three components, the cage's axes) and how
    it is made."""

    field_ut: Required[list[float]]
    trim: bool
    """Closed on the reference magnetometer after the ramp (the cage's trim loop)."""
    track: bool
    """One of a followed sequence (an orbit, a sine): ramped at the slew limit, never settled."""
    keep_time: bool
    """Skipped rather than sent late when its successor is already due (a sine's set-points)."""
    segment: list[float]
    """A sine's set-points: its segment (axis index, frequency Hz)."""


class LoadPayload(TypedDict, total=False):
    """A load channel's set-point: ``channel`` (its device name) to ``current_a`` (A)."""

    channel: Required[str]
    current_a: Required[float]
    track: bool
    """Followed (a panel's current along an orbit), not a step to settle after."""


@dataclass(frozen=True)
class FieldCommand:
    """Set the cage's field ``t_s`` seconds after its step starts."""

    t_s: float
    payload: FieldPayload
    kind: Literal["field"] = "field"


@dataclass(frozen=True)
class LoadCommand:
    """Set a load channel's current ``t_s`` seconds after its step starts."""

    t_s: float
    payload: LoadPayload
    kind: Literal["load"] = "load"


@dataclass(frozen=True)
class EndCommand:
    """The step's last instant, ``t_s`` seconds after it starts."""

    t_s: float
    kind: Literal["end"] = "end"
    payload: Mapping[str, Any] = field(default_factory=dict)
    """Nothing (read only by code that treats every command alike)."""


@dataclass(frozen=True)
class ActionCommand:
    """The step kind's own action (``kind``: the step kind's name) ``t_s`` seconds after its step
    starts, with ``payload``: the step's parameters, or what the kind planned for the action."""

    t_s: float
    kind: str
    payload: dict[str, Any]


Command = FieldCommand | LoadCommand | EndCommand | ActionCommand
"""One thing to do at a time in a step: ``field`` and ``load`` set-points, ``end`` (the step's last
instant), or the step kind's own action (its name)."""


@dataclass(frozen=True)
class StepPlan:
    """A step's commands, time-ordered, and its nominal duration (s)."""

    step: Step
    duration_s: float
    commands: tuple[Command, ...]


@dataclass(frozen=True)
class RigTiming:
    """What a plan needs to know about the rig besides the procedure: the coil current slew limit
    and set-point interval (``[cage]``), the reference magnetometer's sample rate (these three set
    the duration of a cage characterization) and the cage's field limit (uT; None: not known, the
    steps that sweep to it use :data:`DEFAULT_FIELD_LIMIT_UT`). The defaults are those of the
    simulated cage."""

    max_slew_a_per_s: float = 10.0
    step_s: float = 0.05
    reference_rate_hz: float = 20.0
    max_field_ut: float | None = None


DEFAULT_FIELD_LIMIT_UT = 100.0
"""The field limit assumed when a plan is made without a rig configuration (uT)."""


def suggest(word: object, options: list[str] | set[str] | dict[str, Any]) -> str:
    # YAML keys need not be text ("? " makes a null key, "1:" a number)
    close = difflib.get_close_matches(str(word), [str(o) for o in options], n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def coerce(value: Any, p: StepParam, key: str, where: str) -> Any:
    """``value`` of parameter ``key`` as its kind ``p.kind`` wants it, within its bounds and
    choices; else a ProcedureError naming ``where`` (a NotFiniteError for nan and inf)."""
    if p.kind in ("float", "int"):
        return _number(value, p, key, where)
    if p.kind == "str":
        return _text(value, p, key, where)
    if p.kind in ("vec3", "range2", "list_float"):
        return _numbers(value, p, key, where)
    if p.kind == "list_vec3":
        if not isinstance(value, list) or not value:
            raise _bad(where, key, f"must be a list of [x, y, z] points, got {value!r}")
        points = [_numbers(v, StepParam("vec3"), f"{key}[{i}]", where) for i, v in enumerate(value)]
        for i, point in enumerate(points):
            if any((p.minimum is not None and v < p.minimum)
                   or (p.maximum is not None and v > p.maximum) for v in point):  # fmt: skip
                raise _bad(where, f"{key}[{i}]", f"must be {_bounds(p)}, got {point}")
        return points
    if p.kind == "list_str":
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise _bad(where, key, f"must be a list of names, got {value!r}")
        return list(value)
    if p.kind == "dict":
        if not isinstance(value, dict):
            raise _bad(where, key, f"must be a mapping of name: value, got {value!r}")
        return {k: v for k, v in value.items() if k != "__line__"}
    if p.kind == "list_dict":
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise _bad(where, key, "must be a list of mappings")
        return value
    raise AssertionError(p.kind)


def _bad(where: str, key: str, what: str) -> ProcedureError:
    return ProcedureError(f"{where}: '{key}' {what}")


def _not_finite(where: str, key: str, got: Any) -> NotFiniteError:
    return NotFiniteError(
        f"{where}: '{key}' must be a finite number, got {got!r}; {NOT_FINITE_FIX}"
    )


def _number(value: Any, p: StepParam, key: str, where: str) -> int | float:
    """A ``float`` or ``int`` parameter (an int stays exact)."""
    if isinstance(value, str):  # a "{parameter}" substituted from --set or a default
        try:
            number: int | float = float(value)
        except ValueError:
            raise _bad(where, key, f"must be a number, got {value!r}") from None
    elif isinstance(value, bool) or not isinstance(value, int | float):
        raise _bad(where, key, f"must be a number, got {value!r}")
    else:
        number = value
    fv = finite_number(number)
    if fv is None:
        raise _not_finite(where, key, value)
    if p.kind == "int" and not fv.is_integer():
        raise _bad(where, key, f"must be a whole number, got {value!r}")
    v = int(number) if p.kind == "int" else fv  # an int stays exact
    if (p.minimum is not None and v < p.minimum) or (p.maximum is not None and v > p.maximum):
        raise _bad(where, key, f"must be {_bounds(p)}, got {v:g}")
    return v


def _text(value: Any, p: StepParam, key: str, where: str) -> str:
    """A ``str`` parameter (a YAML yes/no is 'yes'/'no'; a number is its text)."""
    if isinstance(value, bool):
        value = "yes" if value else "no"
    if not isinstance(value, str | int | float):
        raise _bad(where, key, f"must be text, got {value!r}")
    text = str(value)
    if p.choices and text not in p.choices:
        options = ", ".join(c or "''" for c in p.choices)
        raise _bad(
            where, key, f"must be one of {options}, got {text!r}{suggest(text, set(p.choices))}"
        )
    return text


def _numbers(value: Any, p: StepParam, key: str, where: str) -> list[float]:
    """A ``vec3``, ``range2`` or ``list_float`` parameter."""
    n = {"vec3": 3, "range2": 2}.get(p.kind)
    if (
        not isinstance(value, list)
        or (n is not None and len(value) != n)
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise _bad(where, key, f"must be a list of {n or 'some'} numbers, got {value!r}")
    finite = [finite_number(v) for v in value]
    vals = [v for v in finite if v is not None]
    if len(vals) != len(finite):
        raise _not_finite(where, key, value)
    if p.kind == "range2":
        if vals[0] > vals[1]:
            raise _bad(where, key, f"must be [low, high], got {value!r}")
        if (p.minimum is not None and vals[0] < p.minimum) or (
            p.maximum is not None and vals[1] > p.maximum
        ):
            raise _bad(where, key, f"must be {_bounds(p)}")
    if p.kind == "list_float" and not vals:
        raise _bad(where, key, "must not be empty")
    return vals


def _bounds(p: StepParam) -> str:
    if p.minimum is not None and p.maximum is not None:
        return f"within {p.minimum:g}..{p.maximum:g}"
    return f"at least {p.minimum:g}" if p.minimum is not None else f"at most {p.maximum:g}"


def bind_params(
    spec: dict[str, StepParam], given: dict[str, Any], where: str, what: str
) -> dict[str, Any]:
    out = {}
    for key in given:
        if key == "__line__":
            continue
        if key not in spec:
            raise ProcedureError(
                f"{where}: {what} has no parameter '{key}'{suggest(key, spec)}; allowed: {', '.join(spec) or 'none'}"
            )
    for key, p in spec.items():
        if key in given:
            out[key] = coerce(given[key], p, key, where)
        elif p.required:
            raise ProcedureError(f"{where}: {what} needs '{key}'")
        else:
            out[key] = p.default
    return out
