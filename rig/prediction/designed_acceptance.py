"""A designed plan as a whole acceptance procedure (``rig design`` with ``acceptance:``, issue 55).

The designed calibration (:mod:`rig.prediction.design`) gives no verdict on its own. With an
``acceptance:`` section in the targets file, ``rig design`` writes a procedure a technician can run
and sign: the replaced procedure's parameters (DUT serial, operator) and mounting prompts, the
cage characterization when the rig's cage model is only nominal, the measurements its criteria read
besides the calibration (``measure:``, else that procedure's own steps), the designed field
set-points with the loads stepping, a calibration under each name the replaced criteria read, and
the check: every criterion of the replaced procedure whose value the designed plan measures, plus
one per sigma target on the designed calibration's combined 1-sigma. A criterion it cannot carry
(one on a live calibration the design replaces) is named in the file's header, never dropped in
silence.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rig.errors import UserInputError

CALIBRATION_KINDS = ("calibrate", "live_calibrate")
DESIGNED_FIELDS = "designed fields"


@dataclass(frozen=True)
class Acceptance:
    """The ``acceptance:`` section of a targets file: the procedure the designed one replaces
    (``replaces``: a file or a shipped name) and, optionally, the measurements to make besides
    the calibration (``measure``: steps as in a procedure; default: those of the replaced
    procedure that its criteria read)."""

    replaces: str
    measure: list[dict[str, Any]] | None = None

    @classmethod
    def from_raw(cls, raw: Any, where: str) -> Acceptance | None:
        """The section as read from YAML (None when absent); UserInputError naming the fault."""
        if raw is None:
            return None
        if not isinstance(raw, dict) or not isinstance(raw.get("replaces"), str):
            raise UserInputError(f"{where}: acceptance: needs 'replaces:', the procedure whose"
                                 " prompts and criteria the designed one keeps, e.g."
                                 " replaces: dut-acceptance")  # fmt: skip
        measure = raw.get("measure")
        if measure is not None and (
            not isinstance(measure, list) or not all(isinstance(s, dict) for s in measure)
        ):
            raise UserInputError(f"{where}: acceptance.measure must be a list of steps, as under"
                                 " a procedure's steps:")  # fmt: skip
        return cls(str(raw["replaces"]), measure)


@dataclass
class Replaced:
    """What the designed acceptance takes from the procedure it replaces."""

    title: str
    parameters: dict[str, Any]
    prompts: list[dict[str, Any]]
    steps: dict[str, dict[str, Any]]
    """Every step by its name (its raw mapping), ``name:`` as the procedure language gives it."""
    criteria: list[dict[str, Any]]
    not_carried: list[str] = field(default_factory=list)


def step_kind(step: dict[str, Any]) -> str:
    """The kind of a raw step mapping (its one key besides ``name`` and ``loads``)."""
    return next(k for k in step if k not in ("name", "loads"))


def _named(steps: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The steps by name: ``name:`` or, as the procedure language names them, ``<kind> <n>``."""
    return {str(s.get("name") or f"{step_kind(s)} {i + 1}"): s for i, s in enumerate(steps)}


def read_replaced(name: str) -> Replaced:
    """The replaced procedure's parameters, prompts, steps and criteria (raw YAML)."""
    import yaml

    from rig.procedure_files import find_procedure

    path = find_procedure(name)
    raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    steps = [s for s in raw.get("steps") or [] if isinstance(s, dict) and s]
    criteria = [c for s in steps if step_kind(s) == "check" for c in s["check"].get("criteria", [])]
    if not criteria:
        raise UserInputError(f"{path}: acceptance.replaces names a procedure with no check step:"
                             " there are no criteria to carry")  # fmt: skip
    return Replaced(str(raw.get("procedure", path.stem)), dict(raw.get("parameters") or {}),
                    [s for s in steps if step_kind(s) == "prompt"], _named(steps), criteria)  # fmt: skip


def other_models(replaced: Replaced, model: str) -> tuple[str, ...]:
    """The calibration models besides ``model`` whose results the replaced criteria read: the
    designed set-points must give those fits too."""
    reads = {str(c["result"]) for c in replaced.criteria}
    found = {str(s["calibrate"].get("model", "vector")) for n, s in replaced.steps.items()
             if n in reads and step_kind(s) == "calibrate"}  # fmt: skip
    return tuple(sorted(found - {model}))


def acceptance_steps(
    acceptance: Acceptance, replaced: Replaced, designed: dict[str, Any], fit_name: str,
    targets_achieved: dict[str, tuple[float, float]],
) -> tuple[list[dict[str, Any]], list[str]]:  # fmt: skip
    """The steps of the designed acceptance and the criteria it could not carry (why, each).

    ``designed``: the designed calibration procedure (parsed YAML); ``fit_name``: its calibrate
    step's name; ``targets_achieved``: each target path with (predicted sigma, target)."""
    base = designed["steps"]
    characterize = [s for s in base if step_kind(s) == "characterize_cage"]
    fields = next(s for s in base if s.get("name") == DESIGNED_FIELDS)
    fit = next(s for s in base if s.get("name") == fit_name)
    reads = {str(c["result"]) for c in replaced.criteria}
    measure = acceptance.measure
    if measure is None:
        measure = [s for n, s in replaced.steps.items()
                   if n in reads and step_kind(s) not in (*CALIBRATION_KINDS, "check")]  # fmt: skip
    if not any(step_kind(s) == "null_field" for s in measure):
        measure = [next(s for s in base if step_kind(s) == "null_field"), *measure]
    fits = _calibrations(replaced, reads, fit, fit_name)
    have = set(_named([*measure, fields, *fits]))
    criteria, not_carried = [], []
    for c in replaced.criteria:
        if str(c["result"]) in have:
            criteria.append(dict(c))
        else:
            kind = (
                step_kind(replaced.steps[str(c["result"])])
                if c["result"] in replaced.steps
                else "?"
            )
            not_carried.append(f"'{c.get('name') or c['value']}' (reads the {kind} step"
                               f" '{c['result']}', which this plan replaces by the sigma targets)")  # fmt: skip
    target_fit = next(
        str(s.get("name")) for s in fits if s["calibrate"]["model"] == fit["calibrate"]["model"]
    )
    for path, (_, limit) in targets_achieved.items():
        criteria.append({"result": target_fit, "value": f"combined_sigma.{path}", "max": limit,
                         "name": f"{path} 1-sigma"})  # fmt: skip
    steps = [*replaced.prompts, *characterize, *measure, fields, *fits,
             {"check": {"criteria": criteria}}, {"report": {}}]  # fmt: skip
    return steps, not_carried


def _calibrations(replaced: Replaced, reads: set[str], fit: dict[str, Any],
                  fit_name: str) -> list[dict[str, Any]]:  # fmt: skip
    """A calibrate step on the designed fields under each name the replaced criteria read from a
    batch calibration (its model and telemetry kept); the designed one first when none does."""
    out: list[dict[str, Any]] = []
    for name, step in replaced.steps.items():
        if name in reads and step_kind(step) == "calibrate":
            params = dict(step["calibrate"]) | {"steps": [DESIGNED_FIELDS]}
            out.append({"calibrate": params, "name": name})
    if not any(s["calibrate"]["model"] == fit["calibrate"]["model"] for s in out):
        out.insert(0, {"calibrate": dict(fit["calibrate"]), "name": fit_name})
    return out


def acceptance_text(targets: Any, design_text: str, fit_name: str,
                    achieved: dict[str, tuple[float, float]],
                    seconds: tuple[float, float, bool] | None = None) -> tuple[str, list[str]]:  # fmt: skip
    """The designed acceptance procedure (YAML text) and the criteria it could not carry;
    ``seconds``: its predicted time on the rig, the replaced procedure's (s) and whether that is
    an upper bound (a live step that may stop sooner), for its description."""
    import yaml

    acceptance: Acceptance = targets.acceptance
    replaced = read_replaced(acceptance.replaces)
    designed = yaml.safe_load(design_text)
    steps, not_carried = acceptance_steps(acceptance, replaced, designed, fit_name, achieved)
    doc = {
        "procedure": f"{replaced.title} (designed)",
        "description": _description(targets.source, acceptance.replaces, seconds),
        "parameters": replaced.parameters,
        "magnetometers": designed["magnetometers"],
    }
    if "loads" in designed:
        doc["loads"] = designed["loads"]
    doc["steps"] = steps
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=1000)
    return text, not_carried


def _description(source: str, replaces: str, seconds: tuple[float, float, bool] | None) -> str:
    """The designed acceptance's description: what it judges, and what each form costs."""
    text = (f"Written by rig design for {Path(source).name}: the criteria of '{replaces}' judged"
            " on the fewest designed field set-points that meet every sigma target, and those"
            " targets judged as criteria.")  # fmt: skip
    if seconds is not None:
        own_s, replaced_s, upper = seconds
        long_form = (f"up to {replaced_s:.0f} s, less when its live step meets its targets"
                     " sooner" if upper else f"about {replaced_s:.0f} s")  # fmt: skip
        text += f" About {own_s:.0f} s on the rig ('{replaces}': {long_form})."
    return text
