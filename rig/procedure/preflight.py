"""What a procedure asks of a rig beyond its limits, worked out once, without hardware: ``rig
check --rig`` prints it, and ``rig run`` refuses it before the lock or any output (one check, one
code path, so a run never starts what the check refuses).

Refused outright (one line, :class:`rig.errors.UserInputError`, exit 2): a configuration naming
one instrument twice (:func:`rig.wire_address.shared_addresses`), a register map of a device that
the one parser refuses (:func:`regmaps.parse_map`: a scale of 0, an address beyond 65535, ...), a
cage device named as a load, a load that is no device. Violations (``LIMIT:`` lines of ``rig check``, exit 1; the first one
refuses a run): fields beyond the cage's field limit, coil currents beyond the cage's current
limits with the cage model's margin, load set-points beyond a channel's own limits (current, sign,
power, the DUT temperature a heater would reach: :mod:`rig.procedure.heat_limits`), and what the
cage cannot do (:mod:`rig.procedure.beyond_cage`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from regmaps import RegisterMapError, load_map
from rig.config import RigConfig
from rig.errors import UserInputError
from rig.output_limits import cage_model, refuse_cage_devices_as_loads
from rig.procedure.beyond_cage import beyond_cage
from rig.procedure.heat_limits import heater_refusals
from rig.procedure.language import FIELD_STEPS, Procedure
from rig.procedure.plan import (
    ABSOLUTE_MAX_FIELD_UT,
    MODEL_SIGMAS,
    CageModelUncertainty,
    DryRun,
    dry_run,
    rig_timing,
)
from rig.wire_address import refuse_shared_addresses


@dataclass(frozen=True)
class CageModelView:
    """The cage model a dry run uses: coil matrix (uT/A), ambient (uT), its uncertainty and where
    it comes from (all None / empty when the rig has no cage model)."""

    k_ut_per_a: Any
    b0_ut: Any
    uncertainty: CageModelUncertainty | None
    source: str


@dataclass(frozen=True)
class Preflight:
    """A procedure checked against a rig: the dry run (timeline, peaks, violations, risks), the
    limits that could not be checked, the cage model and each load's configured limit (A)."""

    dry_run: DryRun
    unchecked: list[str]
    model: CageModelView
    loads_max_a: dict[str, float]

    @property
    def violations(self) -> list[str]:
        """One sentence per limit the procedure would exceed (``rig check``'s ``LIMIT:`` lines)."""
        return self.dry_run.violations


def cage_model_view(cfg: RigConfig | None) -> CageModelView:
    """The cage model for a dry run: the last characterization if there is one, else the nominal
    K with an ambient field not yet known (None for all when the rig has no cage model)."""
    m = cage_model(cfg) if cfg is not None else None
    if m is None or cfg is None or cfg.cage is None:
        return CageModelView(None, None, None, "")
    if m.meta.get("nominal"):
        return CageModelView(m.k_ut_per_a, m.b0_ut, CageModelUncertainty(
            unknown_ambient_ut=cfg.cage.max_ambient_ut), "nominal_k_ut_per_a: no cage"
            " characterization yet, so the lab field (up to [cage] max_ambient_ut ="
            f" {cfg.cage.max_ambient_ut:g} uT) adds to the fields asked and is not cancelled until"
            " the procedure characterizes the cage")  # fmt: skip
    return CageModelView(m.k_ut_per_a, m.b0_ut, CageModelUncertainty(m.k_sigma, m.b0_sigma_ut),
                         f"the cage characterization of {m.meta.get('date', 'undated')}"
                         f" ({cfg.cage.calibration}), currents at {MODEL_SIGMAS:g} sigma of it")  # fmt: skip


def load_limits_a(proc: Procedure, cfg: RigConfig | None) -> dict[str, float]:
    """Each load channel's ``max_current_a`` (A) from the rig configuration, where it has one;
    refuses (UserInputError) a load that is a cage device or no device at all."""
    if cfg is None:
        return {}
    refuse_cage_devices_as_loads(list(proc.loads), cfg, proc.path)
    limits = {}
    for name in proc.loads:
        if name not in cfg.devices:
            raise UserInputError(f"{proc.path}: load '{name}' is not a device in {cfg.path}")
        limit = cfg.devices[name].get("max_current_a")
        if limit is not None:
            limits[name] = float(limit)
    return limits


def unchecked_limits(proc: Procedure, cfg: RigConfig | None, k: Any) -> list[str]:
    """The limits a dry run could not check, one sentence each with the fix."""
    if cfg is None:
        return [
            "no rig configuration given (--rig CONFIG.toml); the rig's field, coil current and"
            f" load current limits were not checked (only |B| <= {ABSOLUTE_MAX_FIELD_UT:g} uT)"
        ]
    if cfg.cage is None:
        return [f"{cfg.path} has no [cage] section; field and coil current limits were not checked"]
    if k is None and any(s.kind in FIELD_STEPS for s in proc.steps):
        return [
            f"{cfg.path} has no cage model ([cage].calibration file or nominal_k_ut_per_a); coil"
            " currents were not checked: run cage-characterization or add nominal_k_ut_per_a"
        ]
    return []


def refuse_bad_register_maps(cfg: RigConfig) -> None:
    """Load every register map the configuration names (``regmap = ...``), as opening its device
    would: a map the parser refuses is a UserInputError naming the device, the map's file and line,
    the register and the fix (issue 51: a map with a scale of 0 or an address of 70000 passed
    ``rig check``; a run found out only when it opened the device)."""
    for dev in cfg.devices.values():
        name = dev.get("regmap")
        if not dev.kind.startswith("regmap-") or not isinstance(name, str):
            continue
        try:
            load_map(name)
        except RegisterMapError as exc:
            raise UserInputError(f"{cfg.path}: [devices.{dev.name}].regmap: {exc}") from None


def preflight(proc: Procedure, cfg: RigConfig | None) -> Preflight:
    """``proc`` checked against ``cfg`` (None: only what holds for any rig). Raises
    UserInputError for what no run may even be recorded with (see the module's text)."""
    if cfg is not None:
        refuse_shared_addresses(cfg)
        refuse_bad_register_maps(cfg)
    model = cage_model_view(cfg)
    loads_max = load_limits_a(proc, cfg)
    cage = cfg.cage if cfg is not None else None
    # each load's own limits (current, sign, power, the DUT's predicted temperature) are
    # heater_refusals' (ADR 0035), not the dry run's: one LIMIT line per problem
    dr = dry_run(proc, model.k_ut_per_a, model.b0_ut, cage.max_current_a if cage else None,
                 cage.max_field_ut if cage else None, {}, rig_timing(cfg),
                 model.uncertainty)  # fmt: skip
    dr.violations.extend(beyond_cage(proc, cfg))
    dr.violations.extend(heater_refusals(proc, cfg))
    return Preflight(dr, unchecked_limits(proc, cfg, model.k_ut_per_a), model, loads_max)


def refuse_what_check_refuses(proc: Procedure, cfg: RigConfig) -> None:
    """Refuse (UserInputError, one line) a procedure ``rig check --rig`` refuses: before the lock,
    the run folder or any output."""
    problems = preflight(proc, cfg).violations
    if problems:
        more = f" (and {len(problems) - 1} more: rig check lists them)" if len(problems) > 1 else ""
        first = problems[0]
        if not first.startswith(str(proc.path)):
            first = f"{proc.path}: {first}"
        raise UserInputError(f"{first}{more}; nothing was switched on: fix the procedure"
                             " (rig check shows every limit)")  # fmt: skip
