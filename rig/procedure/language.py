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
step and the fix. A file is input from anyone: its size, its YAML (nesting, aliases, values with
aliases expanded), its steps, its duration and its load set-points are bounded by the limits in
rig.steps.vocabulary, each checked before the work it bounds, and no nan or inf gets through.
Every string - keys, values, ``--set`` values, step names after substitution - follows the rule
of :mod:`rig.text`: no control characters (free text, as a step's ``StepParam`` declares it, may hold
tab and line feed), and names, serials and other labels at most ``MAX_TEXT_CHARS`` characters.
"""

from __future__ import annotations

import contextlib
import string
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import yaml
from yaml.composer import Composer
from yaml.constructor import SafeConstructor
from yaml.events import AliasEvent
from yaml.nodes import Node, ScalarNode
from yaml.resolver import Resolver

from rig.steps import KINDS
from rig.steps.load_profiles import LOAD_PROFILES, profile_setpoints
from rig.steps.vocabulary import (
    MAX_LOAD_SETPOINTS_PER_STEP,
    MAX_PROCEDURE_FILE_BYTES,
    MAX_STEPS,
    MAX_TOTAL_DURATION_S,
    MAX_YAML_ALIASES,
    MAX_YAML_DEPTH,
    MAX_YAML_NODES,
    NOT_FINITE_FIX,
    NotFiniteError,
    Procedure,
    ProcedureError,
    RigTiming,
    Step,
    StepParam,
    Where,
    bind_params,
    finite_number,
    suggest,
)
from rig.text import FREE_TEXT_CONTROLS, shown, text_problem

__all__ = [
    "NotFiniteError",
    "Procedure",
    "ProcedureError",
    "Step",
    "StepParam",
    "Where",
    "parse_procedure",
]

if yaml.__with_libyaml__:  # libyaml makes the events (no recursion, fast); Python composes them
    from yaml._yaml import CParser as _Events
else:  # pragma: no cover - PyYAML without libyaml
    from yaml.parser import Parser
    from yaml.reader import Reader
    from yaml.scanner import Scanner

    class _Events(Reader, Scanner, Parser):  # type: ignore[no-redef]
        def __init__(self, text: str) -> None:
            Reader.__init__(self, text)
            Scanner.__init__(self)
            Parser.__init__(self)


class _Loader(Composer, _Events, SafeConstructor, Resolver):
    """safe_load with bounds and line numbers. Composing, it refuses (with file:line) nesting
    deeper than :data:`MAX_YAML_DEPTH`, more than :data:`MAX_YAML_ALIASES` aliases, more than
    :data:`MAX_YAML_NODES` values with aliases expanded, an alias inside its own anchor and more
    than :data:`MAX_STEPS` items in the top-level ``steps`` list, each before reading further.
    Constructing, it records each mapping's line under ``__line__`` and each key's line in
    :attr:`key_lines` (by the mapping's ``id``)."""

    def __init__(self, text: str, path: str) -> None:
        _Events.__init__(self, text)
        Composer.__init__(self)
        SafeConstructor.__init__(self)
        Resolver.__init__(self)
        self.path = path
        self.key_lines: dict[int, dict[Any, int]] = {}
        self._depth = self._aliases = self._values = 0
        self._expanded: dict[int, int] = {}  # id(anchored node) -> its values, aliases expanded
        self._in_steps = False

    def _refuse(self, node_line: int, what: str) -> ProcedureError:
        return ProcedureError(f"{self.path}:{node_line}: {what}")

    def _count(self, n: int, line: int) -> None:
        self._values += n
        if self._values > MAX_YAML_NODES:
            raise self._refuse(
                line,
                f"more than {MAX_YAML_NODES} values with YAML aliases expanded (MAX_YAML_NODES;"
                " an alias bomb?): write the values out or use fewer aliases",
            )

    def compose_node(self, parent: Node | None, index: Any) -> Node | None:
        event = self.peek_event()
        if event is None or event.start_mark is None:  # pragma: no cover - the parser gives both
            return super().compose_node(parent, index)
        line = event.start_mark.line + 1
        if isinstance(event, AliasEvent):
            self._aliases += 1
            if self._aliases > MAX_YAML_ALIASES:
                raise self._refuse(
                    line, f"more than {MAX_YAML_ALIASES} YAML aliases (MAX_YAML_ALIASES)"
                )
            node = super().compose_node(parent, index)
            size = self._expanded.get(id(node))
            if size is None:
                raise self._refuse(
                    line, f"alias *{event.anchor} is inside the anchor it names (a loop)"
                )
            self._count(size, line)
            return node
        self._depth += 1
        if self._depth > MAX_YAML_DEPTH:
            raise self._refuse(
                line, f"nested more than {MAX_YAML_DEPTH} levels deep (MAX_YAML_DEPTH)"
            )
        if self._in_steps and self._depth == 3 and isinstance(index, int) and index >= MAX_STEPS:
            raise self._refuse(
                line,
                f"step {index + 1}: a procedure has at most {MAX_STEPS} steps (MAX_STEPS);"
                " split it into several procedures",
            )
        steps = self._depth == 2 and isinstance(index, ScalarNode) and index.value == "steps"
        self._in_steps |= steps
        before = self._values
        self._count(1, line)
        node = super().compose_node(parent, index)
        if steps:
            self._in_steps = False
        if getattr(event, "anchor", None) is not None:
            self._expanded[id(node)] = self._values - before
        self._depth -= 1
        return node

    def construct_object(self, node: Node, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep=deep)
        except (ValueError, OverflowError) as exc:  # !!int of 5000 digits, a 30 February
            text = node.value if isinstance(node, ScalarNode) else node.tag
            raise self._refuse(
                node.start_mark.line + 1,
                f"YAML value {str(text)[:40]!r}: {str(exc).split('; use sys', 1)[0]}",
            ) from None

    def construct_line_map(self, node: yaml.MappingNode) -> Iterator[dict[Any, Any]]:
        data: dict[Any, Any] = {}
        yield data
        data.update(self.construct_mapping(node))
        lines: dict[Any, int] = {}
        for key_node, _ in node.value:
            with contextlib.suppress(TypeError):  # unhashable: construct_mapping refused it
                lines[self.construct_object(key_node)] = key_node.start_mark.line + 1
        data["__line__"] = node.start_mark.line + 1
        self.key_lines[id(data)] = lines


_Loader.add_constructor("tag:yaml.org,2002:map", _Loader.construct_line_map)  # type: ignore[type-var]


def _read_yaml(path: Path) -> tuple[str, dict[str, Any], dict[int, dict[Any, int]]]:
    """The text, the data and the key lines of a procedure file, within the limits."""
    try:
        with path.open("rb") as fh:
            raw = fh.read(MAX_PROCEDURE_FILE_BYTES + 1)  # never more, whatever the file is
    except FileNotFoundError:
        raise ProcedureError(
            f"{path}: no such procedure file; give a path, or run a shipped one by name"
        ) from None
    except OSError as exc:
        raise ProcedureError(f"{path}: cannot read it ({exc.strerror})") from None
    if len(raw) > MAX_PROCEDURE_FILE_BYTES:
        raise ProcedureError(
            f"{path}: larger than {MAX_PROCEDURE_FILE_BYTES} bytes (MAX_PROCEDURE_FILE_BYTES):"
            " a procedure is a short text; split it into several procedures"
        )
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ProcedureError(
            f"{path}: not UTF-8 text (byte {exc.start}): save it as UTF-8"
        ) from None
    loader = _Loader(text, str(path))
    try:
        data = loader.get_single_data()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        if "nesting depth" in problem:  # PyYAML >= 6.0.3 stops deep flow nesting in its scanner
            raise ProcedureError(
                f"{path}{line}: nested more than {MAX_YAML_DEPTH} levels deep (MAX_YAML_DEPTH)"
            ) from None
        raise ProcedureError(
            f"{path}{line}: YAML syntax: {problem}; check indentation and quoting"
        ) from None
    finally:
        loader.dispose()
    if not isinstance(data, dict):
        raise ProcedureError(f"{path}:1: a procedure is a mapping with 'procedure' and 'steps'")
    return text, data, loader.key_lines


def _label(keys: list[Any]) -> str:
    """Where a value sits, as the guide names it: ``step 2 (hold): 'hold_s'``."""

    def dotted(ks: list[Any]) -> str:
        return "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in ks).lstrip(".")

    if len(keys) >= 2 and keys[0] == "steps" and isinstance(keys[1], int):
        head, rest = f"step {keys[1] + 1}", keys[2:]
        if rest and isinstance(rest[0], str) and rest[0] in KINDS:
            head, rest = f"{head} ({rest[0]})", rest[1:]
        return f"{head}: '{dotted(rest)}'" if rest else head
    if len(keys) >= 2 and keys[0] == "parameters":
        return f"parameter '{keys[1]}'" + (f": '{dotted(keys[2:])}'" if keys[2:] else "")
    return f"'{dotted(keys)}'"


def _refuse_non_finite(
    value: Any, keys: list[Any], line: int, path: Path, key_lines: dict[int, dict[Any, int]]
) -> None:
    """A :class:`NotFiniteError` naming the line and the place of the first nan, inf or number
    beyond a float's range anywhere in the file's data (keys included)."""
    if isinstance(value, float | int) and not isinstance(value, bool):
        if finite_number(value) is None:
            digits = str(value)
            shown = (
                repr(value)
                if isinstance(value, float)
                else f"{digits[:8]}... ({len(digits)} digits)"
            )
            raise NotFiniteError(f"{path}:{line}: {_label(keys)} is {shown}; {NOT_FINITE_FIX}")
    elif isinstance(value, dict):
        lines = key_lines.get(id(value), {})
        for k, v in value.items():
            if k != "__line__":
                _refuse_non_finite(k, [*keys, k], lines.get(k, line), path, key_lines)
                _refuse_non_finite(v, [*keys, k], lines.get(k, line), path, key_lines)
    elif isinstance(value, list | tuple | set | frozenset):
        for i, v in enumerate(value):
            _refuse_non_finite(v, [*keys, i], line, path, key_lines)


def _refuse_control_characters(
    value: Any, keys: list[Any], line: int, path: Path, key_lines: dict[int, dict[Any, int]]
) -> None:
    """A :class:`ProcedureError` naming the line and place of the first control character
    anywhere in the file's data (:mod:`rig.text`): keys are labels; values may hold tab and line
    feed here, and are held to their own rule (label or free text) once bound."""
    if isinstance(value, str):
        problem = text_problem(value, label=False, allowed=FREE_TEXT_CONTROLS)
        if problem is not None:
            raise ProcedureError(f"{path}:{line}: {_label(keys)} {shown(value)} {problem}")
    elif isinstance(value, dict):
        lines = key_lines.get(id(value), {})
        for k, v in value.items():
            if k == "__line__":
                continue
            at = lines.get(k, line)
            if isinstance(k, str) and (problem := text_problem(k)) is not None:
                raise ProcedureError(f"{path}:{at}: the key {shown(k)} {problem}")
            _refuse_control_characters(v, [*keys, k], at, path, key_lines)
    elif isinstance(value, list | tuple):
        for i, v in enumerate(value):
            _refuse_control_characters(v, [*keys, i], line, path, key_lines)


def _refuse_bad_labels(value: Any, where: str, what: str) -> None:
    """Every string in ``value`` is a label (:func:`rig.text.text_problem`); ``what`` names it."""
    if isinstance(value, str):
        if (problem := text_problem(value)) is not None:
            raise ProcedureError(f"{where}: {what} {shown(value)} {problem}")
    elif isinstance(value, dict):
        for k, v in value.items():
            if k != "__line__":
                _refuse_bad_labels(v, where, f"'{k}'" if what.startswith("'") else what)
    elif isinstance(value, list | tuple):
        for v in value:
            _refuse_bad_labels(v, where, what)


def _refuse_bad_params_text(
    specs: dict[str, StepParam], params: dict[str, Any], where: str
) -> None:
    """A step's or load profile's bound parameters (``{parameter}`` substituted) against the rule
    of :mod:`rig.text`, as each :class:`StepParam` declares its text (label, free text, file name)."""
    for name, value in params.items():
        spec = specs.get(name)
        kind = spec.text if spec is not None else "label"
        if kind == "label":
            _refuse_bad_labels(value, where, f"'{name}'")
        elif isinstance(value, str):
            allowed = FREE_TEXT_CONTROLS if kind == "free" else ""
            if (problem := text_problem(value, label=False, allowed=allowed)) is not None:
                raise ProcedureError(f"{where}: '{name}' {shown(value)} {problem}")


# --- the vocabulary: step kinds (rig.steps), load profiles (rig.steps.load_profiles) ---------------

COMMON_KEYS = {"name", "loads"}


class _Strict(string.Formatter):
    """``{name}`` and nothing else: no attributes, indexes or format specs (a ``{x:>999999999}``
    would build a gigabyte of text)."""

    def __init__(self, names: dict[str, str], where: str) -> None:
        self.names, self.where = names, where

    def get_field(self, field_name: str, args: Any, kwargs: Any) -> Any:
        if "." in field_name or "[" in field_name:
            raise ProcedureError(
                f"{self.where}: '{{{field_name}}}': a placeholder is a parameter's name, nothing more"
            )
        return super().get_field(field_name, args, kwargs)

    def get_value(self, key: Any, args: Any, kwargs: Any) -> Any:
        if key not in self.names:
            raise ProcedureError(
                f"{self.where}: unknown parameter '{{{key}}}'{suggest(str(key), self.names)}; declare it under 'parameters'"
            )
        return self.names[key]

    def format_field(self, value: Any, format_spec: str) -> Any:
        if format_spec:
            raise ProcedureError(
                f"{self.where}: format '{{...:{format_spec}}}' not allowed: write {{name}} alone"
            )
        return super().format_field(value, format_spec)


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


def _placeholders(value: Any) -> set[str]:
    """The ``{name}`` placeholders in the text anywhere in ``value``."""
    if isinstance(value, str):
        try:
            return {f for _, f, _, _ in string.Formatter().parse(value) if f}
        except ValueError:
            return set()
    if isinstance(value, list):
        return set().union(*(_placeholders(v) for v in value))
    if isinstance(value, dict):
        return set().union(*(_placeholders(v) for v in value.values()))
    return set()


def _with_origin(
    exc: NotFiniteError, raw: Any, names: dict[str, str], origin: dict[str, str]
) -> NotFiniteError:
    """``exc`` naming the parameters behind it: those the step uses whose value is not finite."""
    culprits = []
    for name in sorted(_placeholders(raw) & set(names)):
        try:
            number = float(names[name])
        except ValueError:
            continue
        if finite_number(number) is None:
            culprits.append(f"'{{{name}}}' is {origin[name]}")
    if not culprits:
        return exc
    head, sep, tail = str(exc).partition(f"; {NOT_FINITE_FIX}")
    return NotFiniteError(f"{head} ({', '.join(culprits)}){sep}{tail}")


def parse_procedure(path: str | Path, overrides: dict[str, str] | None = None) -> Procedure:
    """Read, validate and bind a procedure. ``overrides`` set parameters (``--set name=value``).

    Within the limits of rig.steps.vocabulary (docs/procedures.md, "Limits"): the file's size and
    YAML structure as it is read, then no nan or inf anywhere, then per step its parameters, its
    load profiles' set-points and files, and the procedure's duration so far."""
    path = Path(path)
    if (problem := text_problem(path.name)) is not None:
        raise ProcedureError(f"{path}: the file name {problem} (rename the file)")
    text, data, key_lines = _read_yaml(path)
    _refuse_non_finite(data, [], data.get("__line__", 1), path, key_lines)
    _refuse_control_characters(data, [], data.get("__line__", 1), path, key_lines)
    top = Where(str(path), data.get("__line__", 1))
    _check_top(data, top)
    names, origin, may_be_empty = _declared_parameters(data, top, path, key_lines)
    _apply_overrides(overrides or {}, names, origin, may_be_empty, path)
    mags, loads, raw_steps = _roles_loads_and_steps(data, top)
    steps = _parse_steps(raw_steps, path, top, names, origin, loads)
    return Procedure(str(data["procedure"]), path, names, mags, loads, tuple(steps), text)


_TOP_KEYS = {
    "procedure",
    "parameters",
    "magnetometers",
    "loads",
    "steps",
    "__line__",
    "description",
}


def _check_top(data: dict[str, Any], top: Where) -> None:
    """Only known top-level keys, and a title."""
    for key in data:
        if key not in _TOP_KEYS:
            raise ProcedureError(f"{top}: unknown top-level key '{key}'{suggest(key, _TOP_KEYS)}")
    if not isinstance(data.get("procedure"), str):
        raise ProcedureError(f"{top}: needs 'procedure: <title>'")
    _refuse_bad_labels(data["procedure"], str(top), "the title")


def _declared_parameters(
    data: dict[str, Any], top: Where, path: Path, key_lines: dict[int, dict[Any, int]]
) -> tuple[dict[str, str], dict[str, str], set[str]]:
    """The declared parameters' defaults (as text), where each comes from (for error messages),
    and those that may be set empty."""
    declared = data.get("parameters") or {}
    if not isinstance(declared, dict):
        raise ProcedureError(f"{top}: 'parameters' must be a mapping of name: {{default: ...}}")
    names: dict[str, str] = {}
    origin: dict[str, str] = {}
    may_be_empty: set[str] = set()
    for name, spec in declared.items():
        if name == "__line__":
            continue
        default = spec.get("default") if isinstance(spec, dict) else spec
        names[name] = "" if default is None else str(default)
        line = key_lines.get(id(declared), {}).get(name, top.line)
        origin[name] = f"the default of parameter '{name}' ({path}:{line})"
        _refuse_bad_labels(names[name], f"{path}:{line}", f"parameter '{name}': 'default'")
        if isinstance(spec, dict) and spec.get("allow_empty") in (True, "yes"):
            may_be_empty.add(name)
    return names, origin, may_be_empty


def _apply_overrides(overrides: dict[str, str], names: dict[str, str], origin: dict[str, str],
                     may_be_empty: set[str], path: Path) -> None:  # fmt: skip
    """``--set name=value`` for each override, into ``names`` and ``origin``."""
    for name, value in overrides.items():
        if (problem := text_problem(value)) is not None:
            raise ProcedureError(f"{path}: --set {shown(name)}={shown(value)}: the value {problem}")
        if name not in names:
            raise ProcedureError(
                f"{path}: --set {name}=...: the procedure has no parameter '{name}'{suggest(name, names)}"
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
        origin[name] = f"--set {name}={value}"


def _roles_loads_and_steps(
    data: dict[str, Any], top: Where
) -> tuple[dict[str, str], tuple[str, ...], list[Any]]:
    """The magnetometer roles, the load channels and the raw steps, checked."""
    mags = data.get("magnetometers") or {"dut": "dut", "reference": "reference"}
    if not isinstance(mags, dict) or "dut" not in mags:
        raise ProcedureError(f"{top}: 'magnetometers' must map roles to devices and include 'dut'")
    mags = {k: str(v) for k, v in mags.items() if k != "__line__"}
    _refuse_bad_labels(mags, str(top), "'magnetometers'")
    loads = data.get("loads") or []
    if not isinstance(loads, list) or not all(isinstance(x, str) for x in loads):
        raise ProcedureError(f"{top}: 'loads' must be a list of load-channel device names")
    _refuse_bad_labels(loads, str(top), "a load in 'loads'")
    raw_steps = data.get("steps")
    if not isinstance(raw_steps, list) or not raw_steps:
        raise ProcedureError(f"{top}: needs a non-empty 'steps' list")
    if len(raw_steps) > MAX_STEPS:  # the reader stops at the first step beyond; this is a backstop
        raise ProcedureError(
            f"{top}: {len(raw_steps)} steps: a procedure has at most {MAX_STEPS} steps (MAX_STEPS)"
        )
    return mags, tuple(loads), raw_steps


def _parse_steps(raw_steps: list[Any], path: Path, top: Where, names: dict[str, str],
                 origin: dict[str, str], loads: tuple[str, ...]) -> list[Step]:  # fmt: skip
    """Every step bound and validated, the procedure's duration and each step's load set-points
    within their limits."""
    steps: list[Step] = []
    total_s = 0.0
    for i, raw in enumerate(raw_steps):
        try:
            step = _parse_step(i, raw, path, top, names, loads)
        except NotFiniteError as exc:
            raise _with_origin(exc, raw, names, origin) from None
        where = f"{step.where}: step {i + 1} ({step.kind})"
        duration_s = KINDS[step.kind].duration_s(step, RigTiming())
        total_s += duration_s
        if total_s > MAX_TOTAL_DURATION_S:
            raise ProcedureError(
                f"{where}: the procedure's duration reaches {total_s / 86400:.2f} days here,"
                f" beyond the {MAX_TOTAL_DURATION_S / 86400:g}-day limit (MAX_TOTAL_DURATION_S):"
                " shorten it or split it into several procedures"
            )
        _check_setpoints(step, where, duration_s, path)
        KINDS[step.kind].check_against(step, steps)
        steps.append(step)
    return steps


def _check_setpoints(step: Step, where: str, duration_s: float, path: Path) -> None:
    """The step's load profiles make at most MAX_LOAD_SETPOINTS_PER_STEP set-points."""
    setpoints = 0
    for ch, (pkind, pparams) in step.loads.items():
        try:
            setpoints += profile_setpoints(pkind, pparams, duration_s, path.parent)
        except ProcedureError as exc:
            raise type(exc)(f"{where}: load '{ch}': {exc}") from None
        if setpoints > MAX_LOAD_SETPOINTS_PER_STEP:
            raise ProcedureError(
                f"{where}: load '{ch}': the step's load profiles make more than"
                f" {MAX_LOAD_SETPOINTS_PER_STEP} set-points over {duration_s:g} s"
                " (MAX_LOAD_SETPOINTS_PER_STEP): lengthen their dwell, period or step_s"
            )


def _parse_step(
    i: int, raw: Any, path: Path, top: Where, names: dict[str, str], loads: tuple[str, ...]
) -> Step:
    """Step ``i`` bound and validated (its duration and load set-points are checked after)."""
    line = raw.get("__line__", top.line) if isinstance(raw, dict) else top.line
    where = f"{path}:{line}: step {i + 1}"
    if not isinstance(raw, dict):
        raise ProcedureError(f"{where}: a step is a mapping like '- hold: {{hold_s: 5}}'")
    kind = _step_kind(raw, where)
    step_kind = KINDS[kind]
    body = step_kind.shorthand(raw[kind])
    if body is None:
        body = {}
    if not isinstance(body, dict):
        raise ProcedureError(
            f"{where} ({kind}): parameters must be a mapping, e.g. '{kind}: {{...}}'"
        )
    body = _substitute(body, names, where)
    params = bind_params(step_kind.params, body, f"{where} ({kind})", kind)
    step_loads = _step_loads(raw, where, kind, loads)
    step_kind.validate(params, loads, f"{where} ({kind})")
    _refuse_bad_params_text(step_kind.params, params, f"{where} ({kind})")
    for ch, (pkind, pparams) in step_loads.items():
        _refuse_bad_params_text(LOAD_PROFILES[pkind], pparams, f"{where} load '{ch}'")
    name = _substitute(
        str(raw.get("name") or params.get("name") or f"{kind} {i + 1}"), names, where
    )
    if (problem := text_problem(name)) is not None:
        raise ProcedureError(
            f"{where}: the step's name {shown(name)} (parameters substituted) {problem}"
        )
    return Step(i, kind, name, params, step_loads, Where(str(path), line))


def _step_kind(raw: dict[str, Any], where: str) -> str:
    """The one step kind a step's mapping names (its other keys are common ones)."""
    kinds = [k for k in raw if k in KINDS]
    unknown = [k for k in raw if k not in KINDS and k not in COMMON_KEYS and k != "__line__"]
    if unknown:
        raise ProcedureError(
            f"{where}: unknown step or key '{unknown[0]}'{suggest(unknown[0], list(KINDS) + list(COMMON_KEYS))}; steps are: {', '.join(KINDS)}"
        )
    if len(kinds) != 1:
        raise ProcedureError(
            f"{where}: exactly one step kind per list item, found {kinds or 'none'}"
        )
    return kinds[0]


def _step_loads(raw: dict[str, Any], where: str, kind: str,
                loads: tuple[str, ...]) -> dict[str, tuple[str, dict[str, Any]]]:  # fmt: skip
    """A step's load profiles, each bound: channel -> (profile kind, parameters)."""
    step_loads: dict[str, tuple[str, dict[str, Any]]] = {}
    raw_loads = raw.get("loads") or {}
    if not isinstance(raw_loads, dict):
        raise ProcedureError(
            f"{where}: 'loads' of a step maps load channels to profiles, e.g."
            " 'loads: {bus: {constant: {current_a: 1}}}'"
        )
    for ch, prof in raw_loads.items():
        if ch == "__line__":
            continue
        if ch not in loads:
            raise ProcedureError(
                f"{where}: load '{ch}' is not in the procedure's 'loads' list{suggest(ch, list(loads))}"
            )
        if not KINDS[kind].takes_loads:
            raise ProcedureError(
                f"{where}: load profiles run during field steps, not during '{kind}'"
            )
        step_loads[ch] = _load_profile(ch, prof, where)
    return step_loads


def _load_profile(ch: str, prof: Any, where: str) -> tuple[str, dict[str, Any]]:
    """Load ``ch``'s one profile, bound: (profile kind, parameters)."""
    if not isinstance(prof, dict) or len([k for k in prof if k != "__line__"]) != 1:
        raise ProcedureError(
            f"{where}: load '{ch}' needs exactly one profile: {', '.join(LOAD_PROFILES)}"
        )
    pkind = next(k for k in prof if k != "__line__")
    if pkind not in LOAD_PROFILES:
        raise ProcedureError(
            f"{where}: load '{ch}': unknown profile '{pkind}'{suggest(pkind, LOAD_PROFILES)}"
        )
    given = prof[pkind] or {}
    if not isinstance(given, dict):
        raise ProcedureError(
            f"{where}: load '{ch}': the {pkind} profile's parameters must be a mapping, e.g."
            f" '{pkind}: {{...}}'"
        )
    return pkind, bind_params(LOAD_PROFILES[pkind], given, f"{where} load '{ch}'", pkind)


STEP_KINDS = {name: k.params for name, k in KINDS.items()}
"""Parameters of every step kind (for help texts and tools; the kinds live in rig.steps)."""
FIELD_STEPS = {name: k.params for name, k in KINDS.items() if k.takes_loads}
"""Parameters of the kinds that set fields and may carry load profiles."""
