"""``rig check --predict``: the prediction printed (what each calibrate step will report, what
limits it, which criteria cannot pass)."""

from __future__ import annotations

import time
from pathlib import Path

from rig.cli.common import parse_sets


def run_prediction(procedure: str, rig_config: Path | None, sets: list[str], runs_dir: Path,
                   noise_nt: float | None, quiet: bool) -> int:  # fmt: skip
    """Print the prediction; 1 when a criterion cannot pass with this plan, else 0."""
    from rig.config import load_rig_config
    from rig.prediction.procedure import predict_procedure
    from rig.procedure.language import parse_procedure
    from rig.procedure.plan import rig_timing
    from rig.procedure_files import find_procedure
    from rig.steps.vocabulary import RigTiming

    start = time.perf_counter()
    proc = parse_procedure(find_procedure(procedure), parse_sets(sets))
    cfg = load_rig_config(rig_config) if rig_config else None
    pred = predict_procedure(proc, cfg, rig_timing(cfg) or RigTiming(), runs_dir, noise_nt)
    if not quiet:
        print(f"\nprediction (noise {pred.noise.pair_nt:.1f} nT per axis, DUT less reference:"
              f" {pred.noise.source}; {time.perf_counter() - start:.2f} s):")  # fmt: skip
        bg = pred.background
        if bg is not None and (not bg.known or any(bg.field_ut)):
            field = ", ".join(f"{v:.1f}" for v in bg.field_ut)
            print(f"  field at the cage's zero: ({field}) uT, on every set-point not after a"
                  f" characterization: {bg.source}")  # fmt: skip
        for step in pred.steps:
            _print_step(step, pred.noise)
        for live in pred.live:
            _print_live(live)
        d = pred.duration
        low, high = d.range_s
        spread = f" ({low:.0f}-{high:.0f} s over the earlier runs' noises)" if high > low else ""
        stop_note = (f"; the live calibration stopping where predicted, at most {d.total_s:.0f} s"
                " at its max_s" if d.saved_s else "; a live calibration may stop earlier"
                if d.early_stop else "")  # fmt: skip
        print(f"  duration on the rig: about {d.expected_s:.0f} s{spread} (planned"
              f" {d.planned_s:.0f} s, ramps {d.ramps_s:.0f} s, {d.flips} polarity flips,"
              f" {d.trims} trimmed fields){stop_note}")  # fmt: skip
    for c in pred.criteria:
        if c.verdict != "can pass" or not quiet:
            print(f"{'CANNOT PASS' if c.verdict == 'CANNOT PASS' else '  ' + c.verdict}:"
                  f" '{c.name}': {c.text}")  # fmt: skip
    return 1 if pred.cannot_pass else 0


def _print_live(live: object) -> None:
    from rig.prediction.live_calibrate_stop import LivePrediction

    assert isinstance(live, LivePrediction)
    if live.problem is not None:
        print(f"  '{live.step}' (live): {live.problem}")
        return
    when = (f"targets met after about {live.stop_s:.1f} s of dwell (of at most {live.max_s:g} s;"
            f" '{live.limited_by}' decides)" if live.stop_s is not None
            else f"targets NOT met by {live.max_s:g} s: '{live.limited_by}'")  # fmt: skip
    sigmas = ", ".join(f"{k} {v:.3g} ({live.targets.get(k, float('nan')):g})"
                       for k, v in live.sigmas.items())  # fmt: skip
    print(f"  '{live.step}' (live, {live.noise_nt:.1f} nT): {when}; sigma (target): {sigmas}")


def _print_step(step: object, noise: object) -> None:
    from rig.prediction.noise import NoiseFloor
    from rig.prediction.predict import StepPrediction
    from rig.prediction.spread import run_spread

    assert isinstance(step, StepPrediction) and isinstance(noise, NoiseFloor)
    print(f"  '{step.step}' ({step.method}): {step.samples} samples from"
          f" {', '.join(step.steps) or 'no step'} ({step.seconds:.0f} s planned)")  # fmt: skip
    if step.problem is not None:
        print(f"    cannot be fitted: {step.problem}")
        return
    spread = run_spread(noise, step.samples, len(step.parameters))
    print(
        f"    {'value':<30} {'1-sigma':>10} {'one run, 68 %':>19} {'statistical':>12}  limited by"
    )
    for p in step.parameters:
        low, high = spread.range_of(p)
        one_run = f"{low:.3g}-{high:.3g}"
        print(f"    {p.path:<30} {p.combined:10.3g} {one_run:>19} {p.statistical:12.3g}"
              f"  {p.limited_by}")  # fmt: skip
    print(f"    one run, 68 %: where a single run's 1-sigma falls two times in three (the 1-sigma"
          f" column is the typical run's), from {spread.source}")  # fmt: skip
    for why in step.left_out:
        print(f"    not counted: {why}")
