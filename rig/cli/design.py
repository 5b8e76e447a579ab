"""``rig design``: the shortest calibration procedure that meets given sigma targets."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from rig.cli.common import Parser, Subparsers, check_outputs, write_text

if TYPE_CHECKING:
    from rig.prediction.design import Targets
    from rig.steps.vocabulary import Procedure


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    d = sub.add_parser("design", parents=parents,
                       help="write the shortest calibration procedure that meets sigma targets")  # fmt: skip
    d.add_argument("--targets", required=True, metavar="FILE|NAME",
                   help="the targets (YAML: model, loads and their levels, magnitude_ut, targets:"
                        " result value -> largest combined 1-sigma), or a shipped set's name: acceptance"
                        " (rig/shipped_procedures/targets/acceptance.yaml)")  # fmt: skip
    d.add_argument(
        "--rig",
        type=Path,
        required=True,
        metavar="CONFIG.toml",
        help="the rig: its cage model, limits, reference certificate and DUT rate",
    )
    d.add_argument(
        "--max-s",
        type=float,
        metavar="S",
        help="the longest time on the rig the procedure may take (s)",
    )
    d.add_argument("--margin", type=float, default=0.25, metavar="FRACTION",
                   help="size each predicted sigma this much below its target (default 0.25: a"
                        " run's noise varies about the measured floor)")  # fmt: skip
    d.add_argument(
        "--out",
        type=Path,
        metavar="FILE",
        help="write the procedure here (default: standard output)",
    )
    d.add_argument("--noise-nt", type=float, metavar="NT",
                   help="the DUT's noise paired with the reference (nT per axis; default: the"
                        " newest runs' in --runs-dir, else the devices' noise_nt)")  # fmt: skip
    d.add_argument(
        "--runs-dir",
        type=Path,
        default=Path("runs"),
        metavar="DIR",
        help="where earlier runs are, for their measured noise (default: runs)",
    )
    d.set_defaults(func=_cmd_design)


def _cmd_design(args: argparse.Namespace) -> int:
    return run_design(args.targets, args.rig, args.max_s, args.out, args.noise_nt, args.runs_dir,
                      args.quiet, args.margin)  # fmt: skip


def run_design(targets_path: Path | str, rig_config: Path, max_s: float | None, out: Path | None,
               noise_nt: float | None, runs_dir: Path, quiet: bool, margin: float = 0.25) -> int:  # fmt: skip
    """Write the designed procedure; 0 when it meets every target, 1 when none could (nothing
    written: which target binds, and what would meet it)."""
    import dataclasses

    from rig.config import load_rig_config
    from rig.errors import UserInputError
    from rig.prediction.design import Targets, design_procedure
    from rig.prediction.designed_acceptance import other_models, read_replaced
    from rig.prediction.noise import noise_floor
    from rig.prediction.procedure import cage_terms_for
    from rig.procedure.plan import rig_timing
    from rig.procedure_files import TARGETS_DIR, find_targets, shipped_name
    from rig.steps.vocabulary import RigTiming

    if not 0.0 <= margin <= 4.0:
        raise UserInputError(f"--margin must be 0-4 (a fraction), got {margin:g}")
    found = find_targets(str(targets_path))
    targets = Targets.load(found)
    if found.is_relative_to(TARGETS_DIR):  # a shipped set, by name
        targets = dataclasses.replace(targets, source=shipped_name(found))
    also_fit: tuple[str, ...] = ()
    if targets.acceptance is not None:  # the procedure it replaces, checked before the design
        also_fit = other_models(read_replaced(targets.acceptance.replaces), targets.model)
    cfg = load_rig_config(rig_config)
    if out is not None:
        check_outputs([out], exclusive=True)  # a link or a file there: refused before the work
    probe = _probe_procedure(targets)
    noise = noise_floor(probe, cfg, runs_dir, noise_nt)
    timing = rig_timing(cfg) or RigTiming()
    cage = cage_terms_for(probe, cfg)
    overhead_s = 0.0
    if targets.acceptance is not None and max_s is not None:  # --max-s: the whole acceptance's
        first = design_procedure(targets, cfg, timing, noise, cage, None, margin, also_fit)
        overhead_s = _acceptance(first, targets, cfg, timing)[1] - first.seconds
    design = design_procedure(targets, cfg, timing, noise, cage,
                              None if max_s is None else max_s - overhead_s, margin, also_fit)  # fmt: skip
    if not design.meets:
        # no runnable file that claims what it cannot give: what binds, and what would meet it
        untimed = design_procedure(targets, cfg, timing, noise, cage, None, margin, also_fit)
        print(f"rig design: no plan meets every target{_within(max_s)}; nothing written."
              f" {_what_binds(design, untimed, margin)}", file=sys.stderr)  # fmt: skip
        return 1
    body, seconds, not_carried = design.text, design.seconds, list[str]()
    if targets.acceptance is not None:
        body, seconds, not_carried = _acceptance(design, targets, cfg, timing)
    text = _with_header(design, targets, noise, margin, seconds, not_carried) + body
    if out is None:
        sys.stdout.write(text)
    else:
        write_text(out, text, exclusive=True)  # never through a link, never over a file
    if not quiet:
        what = "an acceptance with" if targets.acceptance is not None else ""
        print(f"rig design: {what} {design.points} set-points of {design.dwell_s:g} s, about"
              f" {seconds:.0f} s on the rig; meets every target"
              + (f"; written to {out}" if out is not None else ""), file=sys.stderr)  # fmt: skip
    return 0


def _acceptance(design: object, targets: Targets, cfg: object,
                timing: object) -> tuple[str, float, list[str]]:  # fmt: skip
    """The designed acceptance (YAML), its predicted time on the rig (s) and the criteria it
    could not carry; the text is parsed as ``rig run`` would (a criterion naming no step is
    refused here, not on the rig)."""
    import tempfile

    from rig.output_limits import cage_model
    from rig.prediction.design import Design
    from rig.prediction.designed_acceptance import acceptance_text
    from rig.prediction.duration import PredictedDuration, predicted_duration
    from rig.prediction.procedure import cage_limits
    from rig.procedure.language import parse_procedure
    from rig.procedure_files import find_procedure

    assert isinstance(design, Design) and targets.acceptance is not None
    model, limits = cage_model(cfg), cage_limits(cfg)  # type: ignore[arg-type]

    def seconds_of(path: Path) -> PredictedDuration:
        return predicted_duration(parse_procedure(path), model, limits, timing)  # type: ignore[arg-type]

    text, _ = acceptance_text(targets, design.text, "calibration", design.achieved)
    with tempfile.TemporaryDirectory(prefix="rig-design-") as tmp:
        path = Path(tmp) / "acceptance.yaml"
        path.write_text(text)
        own, replaced = seconds_of(path), seconds_of(find_procedure(targets.acceptance.replaces))
    seconds = (own.total_s, replaced.total_s, replaced.early_stop)
    text, not_carried = acceptance_text(targets, design.text, "calibration", design.achieved,
                                        seconds)  # fmt: skip
    return text, own.total_s, not_carried


def _within(max_s: float | None) -> str:
    return f" within --max-s {max_s:g}" if max_s is not None else ""


def _what_binds(timed: object, untimed: object, margin: float) -> str:
    """Which target binds and what would meet it: more time (the shortest plan that meets every
    target without the time limit), or, for a target no number of points meets, its limiting
    term and the smallest target the plan could give."""
    from rig.prediction.design import Design

    assert isinstance(timed, Design) and isinstance(untimed, Design)
    if untimed.meets:
        return (f"The shortest plan that meets every target takes about {untimed.seconds:.0f} s"
                f" ({untimed.points} set-points of {untimed.dwell_s:g} s): give --max-s"
                f" {math.ceil(untimed.seconds)} or more.")  # fmt: skip
    lines = []
    for what, why in untimed.unmet.items():
        got = untimed.achieved.get(what)
        reach = (f"; the best a plan gives: {got[0]:.3g}, a target of {got[0] * (1 + margin):.3g}"
                 f" with the {100 * margin:.0f} % margin" if got is not None else "")  # fmt: skip
        lines.append(f"{what}: {why}{reach}")
    fix = ("a better reference (its certificate)" if any("certificate" in w for w in lines)
           else "a quieter DUT or more set-points than 400")  # fmt: skip
    return (
        f"Not met by any number of set-points: {'; '.join(lines)}. What would meet it: a"
        f" target at least as large as the most a plan gives, or {fix}."
    )


def _probe_procedure(targets: Targets) -> Procedure:
    """A procedure naming the roles and loads the targets use (for the noise floor's lookup and
    the cage's terms)."""
    import tempfile

    import numpy as np

    from rig.prediction.design import procedure_text
    from rig.procedure.language import parse_procedure

    text = procedure_text(targets, np.eye(3) * targets.magnitude_ut[1], 1.0, False, [])
    with tempfile.TemporaryDirectory(prefix="rig-design-") as tmp:
        path = Path(tmp) / "probe.yaml"
        path.write_text(text)
        return parse_procedure(path)


def _with_header(design: object, targets: object, noise: object, margin: float,
                 seconds: float, not_carried: list[str]) -> str:  # fmt: skip
    """The comment block above the procedure: how it was designed, what it is predicted to give,
    (an acceptance) what it replaces and which of its criteria it could not carry."""
    from rig.prediction.design import Design, Targets
    from rig.prediction.noise import NoiseFloor

    assert isinstance(design, Design) and isinstance(targets, Targets)
    assert isinstance(noise, NoiseFloor)
    lines = [f"Designed by rig design for {targets.source}: {design.points} field set-points"
             f" (D-optimal, Fedorov exchange), {design.dwell_s:g} s each;"
             f" about {seconds:.0f} s on the rig.",
             f"Noise floor {noise.pair_nt:.1f} nT per axis ({noise.source}).",
             f"Predicted combined 1-sigma against each target (sized {100 * margin:.0f} % below"
             " it: a run's noise varies about the floor):"]  # fmt: skip
    for path, (got, limit) in design.achieved.items():
        lines.append(f"  {path}: {got:.3g} (target {limit:g})")
    if targets.acceptance is not None:
        lines.append(f"Replaces '{targets.acceptance.replaces}': its parameters, prompts and"
                     " criteria, each sigma target above a criterion too.")  # fmt: skip
        lines += [f"Not carried: {why}" for why in not_carried]
    return "".join(f"# {line}\n" for line in lines)
