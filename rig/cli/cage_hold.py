"""``rig cage hold``: hold a field and measure how well it holds; ``--servo`` holds it against the
lab field's changes (:mod:`rig.cage.servo`). Outputs go safe on every exit; Ctrl-C ends the hold
and still prints and writes what was measured."""

from __future__ import annotations

import csv
import io
import sys
from pathlib import Path
from typing import Any

import numpy as np

import timebase
from rig.cli.common import check_outputs, write_text
from rig.errors import UserInputError

BIAS_A = 0.5
"""The trims' working point (A): half their servo range either way (a 2 uT/A trim: +-1 uT)."""


def _check(cfg: Any, servo: bool) -> tuple[Any, str, str]:
    """The ``[cage]`` table, the inner and the outside reference's names; a one-line error for
    what is missing."""
    cage = cfg.cage
    if cage is None or cage.reference is None or cage.ambient is None:
        raise UserInputError(f"{cfg.path}: rig cage hold needs [cage] reference (inside) and"
                             " ambient (outside the coils)")  # fmt: skip
    if servo and (cage.trim is None or cage.trim_ut_per_a is None):
        raise UserInputError(f"{cfg.path}: --servo needs trim windings: [cage] trim = {{ x = ...,"
                             " y = ..., z = ... }} and trim_ut_per_a")  # fmt: skip
    return cage, str(cage.reference), str(cage.ambient)


def run_hold(rig_config: Path, field_ut: list[float], servo: bool, duration_s: float | None,
             period_s: float, report_s: float, csv_path: Path | None, quiet: bool) -> int:  # fmt: skip
    """Set the field (trimmed on the inner reference), hold it, print the rms of ``report_s``
    means of the inner reference about the target and, with ``--servo``, the same without the
    servo's correction, measured in the same run. 0 when done, 130 after Ctrl-C."""
    from rig.cage.servo import AmbientServo, ServoSettings
    from rig.cli.signals import stop_on_signals
    from rig.config import load_rig_config
    from rig.engine.session import RigSession

    cfg = load_rig_config(rig_config)
    cage, inner_name, outside_name = _check(cfg, servo)
    check_outputs([csv_path])  # a planted link refuses the hold before the cage is driven
    if not 0.05 <= period_s <= 10.0 or report_s < 2 * period_s:
        raise UserInputError("--period must be 0.05-10 s and --report-s at least two periods")
    target = np.array(field_ut, float)
    stop = timebase.Event()
    with stop_on_signals(stop, interrupt=False), RigSession(cfg, command="rig cage hold") as rig:
        controller = rig.cage()
        trims = [rig.load(name) for name in (cage.trim or ())]
        for trim in trims:
            trim.set_current(BIAS_A)
        result = controller.trim(target, tolerance_nt=5.0)  # the trims' bias included
        inner, outside = rig.magnetometer(inner_name), rig.magnetometer(outside_name)
        for sensor, name in ((outside, outside_name), (inner, inner_name)):
            sensor.start_sampling(float(cfg.devices[name].get("rate_hz", 20.0)))
        settings = ServoSettings(cage.trim_ut_per_a or (1.0, 1.0, 1.0), period_s,
                                 0.25 if servo else 0.0, BIAS_A)  # fmt: skip
        loop = AmbientServo(inner, controller.to_cage, outside,
                            trims if servo else [], settings, rig.sleep)  # fmt: skip
        if not quiet:
            print(f"holding {np.round(target, 3).tolist()} uT (trimmed to {result.error_nt:.1f} nT)"
                  + (" with the ambient servo" if servo else "") + "; Ctrl-C ends it")  # fmt: skip
        record = loop.hold(target, duration_s, stop, None if quiet else _progress(duration_s))
    if csv_path is not None:
        _write_csv(csv_path, record)
    _summary(record, target, report_s, servo, quiet)
    return 130 if stop.is_set() else 0


def _progress(duration_s: float | None) -> Any:
    def show(elapsed_s: float) -> None:
        of = "" if duration_s is None else f" of {duration_s:.0f}"
        sys.stderr.write(f"\r  {elapsed_s:.0f}{of} s held")
        sys.stderr.flush()

    return show


def _write_csv(path: Path, record: Any) -> None:
    """The hold's readings (uT) as CSV, written atomically and never through a link."""
    f = io.StringIO(newline="")
    out = csv.writer(f)
    out.writerow(["t_s", *(f"inner_{a}_ut" for a in "xyz"),
                  *(f"outside_change_{a}_ut" for a in "xyz"), *(f"applied_{a}_ut" for a in "xyz")])  # fmt: skip
    for row in zip(record.t_s, record.inner_ut, record.outside_change_ut, record.applied_ut,
                   strict=True):  # fmt: skip
        out.writerow([f"{row[0]:.3f}", *(f"{v:.6f}" for part in row[1:] for v in part)])
    write_text(path, f.getvalue())


def _summary(record: Any, target: Any, report_s: float, servo: bool, quiet: bool) -> None:
    held = record.rms_nt(target, report_s)
    line = (f"held {record.t_s[-1]:.0f} s: rms of {report_s:g} s means about the target"
            f" {', '.join(f'{a} {v:.2f}' for a, v in zip('xyz', held, strict=True))} nT")  # fmt: skip
    if servo:
        free = record.rms_nt(target, report_s, servoed=False)
        line += (f"; without the servo (measured: inner less the trims' field)"
                 f" {', '.join(f'{a} {v:.2f}' for a, v in zip('xyz', free, strict=True))} nT")  # fmt: skip
        if record.saturated:
            line += f"; the trims ran out of range in {record.saturated} periods"
    if not quiet:
        sys.stderr.write("\n")
    print(line)
