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

import string
from pathlib import Path
from typing import Any

import yaml

from rig.steps import KINDS
from rig.steps.load_profiles import LOAD_PROFILES
from rig.steps.vocabulary import (
    Param,
    Procedure,
    ProcedureError,
    Step,
    Where,
    bind_params,
    suggest,
)

__all__ = ["Param", "Procedure", "ProcedureError", "Step", "Where", "parse_procedure"]


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


# --- the vocabulary: step kinds (rig.steps), load profiles (rig.steps.load_profiles) ---------------

COMMON_KEYS = {"name", "loads"}


class _Strict(string.Formatter):
    def __init__(self, names: dict[str, str], where: str) -> None:
        self.names, self.where = names, where

    def get_value(self, key: Any, args: Any, kwargs: Any) -> Any:
        if key not in self.names:
            raise ProcedureError(
                f"{self.where}: unknown parameter '{{{key}}}'{suggest(str(key), self.names)}; declare it under 'parameters'"
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
            raise ProcedureError(f"{top}: unknown top-level key '{key}'{suggest(key, allowed)}")
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
        kind = kinds[0]
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
        step_loads: dict[str, tuple[str, dict[str, Any]]] = {}
        for ch, prof in (raw.get("loads") or {}).items():
            if ch == "__line__":
                continue
            if ch not in loads:
                raise ProcedureError(
                    f"{where}: load '{ch}' is not in the procedure's 'loads' list{suggest(ch, loads)}"
                )
            if not step_kind.takes_loads:
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
                    f"{where}: load '{ch}': unknown profile '{pkind}'{suggest(pkind, LOAD_PROFILES)}"
                )
            step_loads[ch] = (
                pkind,
                bind_params(LOAD_PROFILES[pkind], prof[pkind] or {}, f"{where} load '{ch}'", pkind),
            )
        step_kind.validate(params, tuple(loads), f"{where} ({kind})")
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


STEP_KINDS = {name: k.params for name, k in KINDS.items()}
"""Parameters of every step kind (for help texts and tools; the kinds live in rig.steps)."""
FIELD_STEPS = {name: k.params for name, k in KINDS.items() if k.takes_loads}
"""Parameters of the kinds that set fields and may carry load profiles."""
