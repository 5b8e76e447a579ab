"""What a procedure asks of the cage beyond what it can do (a sine above its measured bandwidth,
faster than its supplies may slew), from the rig configuration and the cage record: printed by
``rig check``, refused before a run starts (nothing locked or switched on)."""

from __future__ import annotations

from rig.config import RigConfig
from rig.errors import UserInputError
from rig.output_limits import cage_model
from rig.steps import KINDS, beyond_the_cage
from rig.steps.base import CageAbilities
from rig.steps.vocabulary import Procedure


def cage_abilities(cfg: RigConfig | None) -> CageAbilities:
    """The cage's model, slew limit and metrology as the rig configuration and its record give
    them (nothing known without a ``[cage]`` section)."""
    cage = cfg.cage if cfg is not None else None
    if cfg is None or cage is None:
        return CageAbilities(None, None)
    model = cage_model(cfg)
    measured = model is not None and not model.meta.get("nominal")
    return CageAbilities(None if model is None else model.k_ut_per_a, cage.max_slew_a_per_s,
                         {} if model is None else model.metrology(),
                         b0_ut=model.b0_ut if measured and model is not None else None,
                         polarity_relays=cage.polarity is not None,
                         coil_tau_s=cage.coil_tau_s)  # fmt: skip


def beyond_cage(proc: Procedure, cfg: RigConfig | None) -> list[str]:
    """One sentence per thing the procedure asks beyond the cage, each naming the fix."""
    return beyond_the_cage(proc, cage_abilities(cfg))


def refuse_beyond_cage(proc: Procedure, cfg: RigConfig) -> None:
    """Refuse (UserInputError, one line) a procedure asking the cage for more than it can do."""
    problems = beyond_cage(proc, cfg)
    if problems:
        more = f" (and {len(problems) - 1} more: rig check lists them)" if len(problems) > 1 else ""
        raise UserInputError(f"{proc.path}: {problems[0]}{more}")


def unmeasured_metrology(proc: Procedure, cfg: RigConfig | None) -> list[str]:
    """A warning per step held to a cage metrology result (its kind's ``cage_metrology_used``)
    that neither the cage record nor an earlier step of the procedure has."""
    known = cage_abilities(cfg).metrology
    out, measured = [], set()
    for step in proc.steps:
        used = KINDS[step.kind].cage_metrology_used
        if used is not None and used not in known and used not in measured:
            out.append(f"step '{step.name}' ({step.kind}) is held to the cage's {used}, which the"
                       f" cage record does not have yet: measure it ({used} step,"
                       " rig run cage-response); until then only the step's own view of"
                       " the cage decides which of its points are judged")  # fmt: skip
        measured.add(step.kind)
    return out
