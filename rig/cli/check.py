"""``rig check``: dry-run a procedure (timeline, duration, peaks against the rig's limits)."""

from __future__ import annotations

import argparse
import datetime as dt
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rig.cli.common import Parser, Subparsers, parse_sets

if TYPE_CHECKING:
    from rig.config import RigConfig
    from rig.procedure.language import Procedure
    from rig.procedure.plan import DryRun


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    chk = sub.add_parser(
        "check", parents=parents, help="dry-run a procedure: timeline, duration, limits"
    )
    chk.add_argument("procedure", metavar="PROCEDURE",
                     help="a procedure file, or the name of a shipped one (e.g. dut-acceptance)")  # fmt: skip
    chk.add_argument(
        "--rig",
        type=Path,
        metavar="CONFIG.toml",
        help="check currents and fields against its limits",
    )
    chk.add_argument("--protections", action="store_true",
                     help="with --rig: also read every supply's and load's protection levels"
                          " (OVP, OCP, OPP) from the instrument and warn where one is above the"
                          " rig's limit for that output (opens the devices; switches nothing)")  # fmt: skip
    chk.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                     help="give a procedure parameter a value (repeat for several)")  # fmt: skip
    chk.add_argument("--predict", action="store_true",
                     help="predict the sigma of every parameter each calibrate step will report,"
                          " what limits it, and whether each criterion can pass (exit 1 if one"
                          " cannot)")  # fmt: skip
    chk.add_argument("--noise-nt", type=float, metavar="NT",
                     help="with --predict: the DUT's noise paired with the reference (nT per"
                          " axis; default: the vector calibration residuals of the newest 5 runs"
                          " of the DUT in --runs-dir pooled, else the newest null_field noise"
                          " there, else the devices' noise_nt)")  # fmt: skip
    chk.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR",
                     help="with --predict: where earlier runs are, for their measured noise floor"
                          " (default: runs)")  # fmt: skip
    chk.set_defaults(func=_cmd_check)


def _cmd_check(args: argparse.Namespace) -> int:
    code = run_check(args.procedure, args.rig, args.set, args.quiet, args.protections)
    if args.predict:
        from rig.cli.prediction_view import run_prediction

        code = max(code, run_prediction(args.procedure, args.rig, args.set, args.runs_dir,
                                        args.noise_nt, args.quiet))  # fmt: skip
    return code


def stale_cage_model(cfg: RigConfig | None, now: dt.datetime | None = None) -> str | None:
    """A warning when the cage's characterization or one of its metrology results (coil axes,
    field map, supply stability) is older than ``[cage] calibration_valid_days`` (or undated),
    None when all are fresh or there is no record."""
    from rig.output_limits import cage_model

    m = cage_model(cfg) if cfg is not None else None
    if m is None or cfg is None or cfg.cage is None or m.meta.get("nominal"):
        return None
    valid = cfg.cage.calibration_valid_days
    now = now or dt.datetime.now(dt.UTC)
    parts = [_stale("the cage model", m.meta.get("date"), valid, now,
                    "characterize the cage (rig run cage-characterization)")]  # fmt: skip
    parts += [_stale(f"its {kind.replace('_', ' ')} result", entry.get("date"), valid, now,
                     f"measure it again ({METROLOGY_PROCEDURES.get(kind, 'its procedure')})")
              for kind, entry in m.metrology().items()]  # fmt: skip
    said = [p for p in parts if p is not None]
    return "; ".join(said) if said else None


METROLOGY_PROCEDURES = {"coil_axes": "rig run cage-metrology", "field_map": "rig run cage-field-map",
                        "supply_stability": "rig run cage-supply-stability",
                        "cage_response": "rig run cage-response"}  # fmt: skip
"""The shipped procedure that measures each metrology result of the cage record."""


def _stale(what: str, when: Any, valid: float, now: dt.datetime, fix: str) -> str | None:
    try:
        date = dt.datetime.fromisoformat(str(when))
    except ValueError:
        return f"{what} has no date: {fix} before trusting it"
    if date.tzinfo is None:
        date = date.replace(tzinfo=dt.UTC)
    age_days = (now - date).total_seconds() / 86400.0
    if age_days <= valid:
        return None
    return (f"{what} of {date.date()} is {age_days:.0f} days old, past its validity"
            f" ([cage] calibration_valid_days = {valid:g}): {fix}")  # fmt: skip


def run_check(procedure: str, rig_config: Path | None, sets: list[str], quiet: bool,
              protections: bool = False) -> int:  # fmt: skip
    """Dry run: timeline, duration, peaks against limits. Exit 0 only when every limit was checked
    and holds; 1 on a violation or when limits could not be checked (no ``--rig``, no cage model;
    with ``protections``, an instrument whose protection levels could not be read). The rig
    configuration is loaded (and checked) against the declared keys (:mod:`rig.config`); the
    limits are :func:`rig.procedure.preflight.preflight`'s, which ``rig run`` refuses by. A
    protection level looser than its output's limit (configured, or with ``protections`` read from
    the instrument) is a ``WARNING`` line naming where it is, its value and the fix."""
    from rig.config import load_rig_config
    from rig.procedure.beyond_cage import unmeasured_metrology
    from rig.procedure.language import parse_procedure
    from rig.procedure.preflight import preflight
    from rig.procedure_files import find_procedure

    proc = parse_procedure(find_procedure(procedure), parse_sets(sets))
    cfg = load_rig_config(rig_config) if rig_config else None
    checked = preflight(proc, cfg)  # what rig run refuses too, by the same code
    dr, unchecked = checked.dry_run, list(checked.unchecked)
    loose = _protection_warnings(cfg, protections, unchecked)
    if not quiet:
        _print_plan(proc, dr, cfg, checked.model.k_ut_per_a, checked.model.source,
                    checked.loads_max_a)  # fmt: skip
    for v in dr.violations:
        print(f"LIMIT: {v}")
    for r in dr.at_risk:
        print(f"AT RISK: {r}")
    for u in unchecked:
        print(f"NOT CHECKED: {u}")
    if (stale := stale_cage_model(cfg)) is not None:
        print(f"WARNING: {stale}")
    for missing in unmeasured_metrology(proc, cfg):
        print(f"WARNING: {missing}")
    for warning in loose:
        print(f"WARNING: {warning}")
    if not quiet:
        print(_verdict(dr, unchecked, cfg))
    return 0 if not dr.violations and not unchecked else 1


def _protection_warnings(cfg: RigConfig | None, read: bool, unchecked: list[str]) -> list[str]:
    """The protection levels looser than their outputs' limits: the configured ones, and with
    ``read`` the instruments' own (an output that could not be read is added to ``unchecked``)."""
    from rig.output_limits import configured_protection_findings

    if cfg is None:
        if read:
            unchecked.append("--protections needs --rig CONFIG.toml: no instrument was read")
        return []
    found = configured_protection_findings(cfg)
    if read:
        from rig.devices import instrument_protection_findings

        read_found, unread = instrument_protection_findings(cfg)
        found += read_found
        unchecked += unread
    return found


def _print_plan(proc: Procedure, dr: DryRun, cfg: RigConfig | None, k: Any, model_source: str,
                loads_max: dict[str, float]) -> None:  # fmt: skip
    """The timeline, the peaks and their limits."""
    cage = cfg.cage if cfg is not None else None
    live = any(s.kind == "live_calibrate" for s in proc.steps)
    how_long = "at most" if live else "about"
    print(
        f"{proc.title} ({proc.path}): {len(proc.steps)} steps, {how_long} {dr.duration_s:.0f} s"
        + (" (live_calibrate steps may stop earlier)" if live else "")
    )
    for t, name, summary in dr.timeline:
        print(f"  {t:7.1f} s  {name:<28} {summary}")
    print(
        f"peak |B| {dr.peak_field_ut:.1f} uT" + (f" (limit {cage.max_field_ut:g})" if cage else "")
    )
    if k is not None:
        print(f"cage model: {model_source}")
        print("peak coil currents " + ", ".join(
            f"{'xyz'[i]} {a:.3f}" + (f" +-{m:.3f}" if m >= 0.0005 else "") + " A"
            for i, (a, m) in enumerate(zip(dr.peak_current_a, dr.peak_margin_a, strict=True)))
              + (f" (limits {', '.join(f'{x:g}' for x in cage.max_current_a)} A)" if cage else ""))  # fmt: skip
    for ch, amps in dr.peak_load_a.items():
        limit_text = f" (limit {loads_max[ch]:g})" if ch in loads_max else ""
        print(f"peak load {ch} {amps:.3f} A{limit_text}")
    no_limit = [ch for ch in dr.peak_load_a if ch not in loads_max]
    if no_limit and cfg is not None:
        print(
            f"note: {', '.join(no_limit)} {'has' if len(no_limit) == 1 else 'have'} no"
            f" max_current_a in {cfg.path}: only the instrument limits the current"
        )


def _verdict(dr: DryRun, unchecked: list[str], cfg: RigConfig | None) -> str:
    """The last line: violations, not checked, at risk or OK."""
    if dr.violations:
        return f"{len(dr.violations)} limit violation(s): fix the procedure"
    if unchecked:
        return "limits NOT CHECKED (see above): not known to be safe on the rig"
    if dr.at_risk:
        return ("OK with the model as it is, but AT RISK (above) once the"
                " ambient field is measured: characterize the cage (rig cage characterize) and"
                " check again, or lower those fields")  # fmt: skip
    return f"OK: within the limits of {cfg.path if cfg else '?'}"
