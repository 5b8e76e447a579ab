"""Every kind of procedure step, by name: the one place a new kind is registered.

To add a kind, write one module here with a :class:`rig.steps.base.StepKind` subclass and a
``KIND`` instance, and add the module's name to :data:`STEP_MODULES` below (docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import replace
from importlib import import_module

from rig.steps.base import CageAbilities, StepKind
from rig.steps.vocabulary import Procedure, Step

STEP_MODULES: tuple[str, ...] = (
    "prompt", "null_field", "set_field", "hold", "sphere_sweep", "field_points", "axis_sweep",
    "rotate", "orbit_replay", "closed_loop", "live_calibrate", "noise_spectrum", "stability",
    "cross_field", "perming", "thermal_cycle", "frequency_response", "linearity",
    "characterize_cage", "coil_axes", "coil_scalar", "field_map", "supply_stability",
    "cage_response", "calibrate", "check", "report",
)  # fmt: skip
"""The modules of ``rig.steps`` that each define a kind (``KIND``), in the order kinds are listed
(a module left out is named by tests/test_step_registry.py)."""


def _kinds() -> dict[str, StepKind]:
    kinds: dict[str, StepKind] = {}
    for module_name in STEP_MODULES:
        kind = import_module(f"rig.steps.{module_name}").KIND
        if not isinstance(kind, StepKind):
            raise TypeError(f"rig/steps/{module_name}.py: KIND is not a StepKind")
        kinds[kind.name] = kind
    return kinds


KINDS: dict[str, StepKind] = _kinds()


def cage_model_measured_before(proc: Procedure, step: Step) -> bool:
    """A step of ``proc`` before ``step`` measures the cage model (its kind's
    ``measures_cage_model``): the run then sets fields with the model it measured."""
    return any(KINDS[s.kind].measures_cage_model for s in proc.steps if s.index < step.index)


def field_kinds() -> frozenset[str]:
    """Kinds that set fields with load profiles running: their samples are 'every field step'."""
    return frozenset(name for name, k in KINDS.items() if k.takes_loads)


def beyond_the_cage(proc: Procedure, cage: CageAbilities) -> list[str]:
    """What the procedure's steps ask of the cage beyond what it can do (each kind's
    ``beyond_cage``; a metrology result a step before measures in the same run is not held
    against the steps after it), one sentence each."""
    out: list[str] = []
    measured: set[str] = set()
    b0_ut = cage.b0_ut  # the record's lab field, until a step measures the cage again
    for step in proc.steps:
        kind = KINDS[step.kind]
        out += kind.beyond_cage(step, replace(cage, measured_before=frozenset(measured),
                                              b0_ut=b0_ut))  # fmt: skip
        measured.add(step.kind)
        if kind.measures_cage_model:
            b0_ut = None
    return out
