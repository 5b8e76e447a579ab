"""``rig cage``: characterize the cage, set or null a field, with the safe state on every exit."""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import ExitStack
from pathlib import Path
from types import FrameType

import numpy as np

from drivers.errors import DeviceError
from rig.cage.characterize import characterize
from rig.config import load_rig_config
from rig.devices import build_cage
from rig.errors import RigError, UserInputError


def _progress(done: int, total: int) -> None:
    width = 30
    filled = int(width * done / total)
    sys.stderr.write(f"\r  [{'#' * filled}{'.' * (width - filled)}] {done}/{total} points")
    if done == total:
        sys.stderr.write("\n")
    sys.stderr.flush()


def _stop_on_signals(stop: threading.Event) -> dict[int, object]:
    def handler(signum: int, frame: FrameType | None) -> None:
        stop.set()
        raise KeyboardInterrupt

    return {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}


def run_characterize(
    rig_config: Path, amplitude_a: float, samples: int, repeats: int, quiet: bool
) -> int:
    """Sweep, fit ``B = K I + B0``, print it, save a new versioned calibration file."""
    cfg = load_rig_config(rig_config)
    if cfg.cage is None or cfg.cage.calibration is None:
        raise UserInputError(
            f"{rig_config}: [cage] needs 'calibration = \"FILE.json\"' to save the result"
        )
    if not 0 < amplitude_a <= min(cfg.cage.max_current_a):
        raise UserInputError(
            f"--amplitude {amplitude_a:g} A must be positive and within the {min(cfg.cage.max_current_a):g} A limit"
        )
    stop = threading.Event()
    old = _stop_on_signals(stop)
    try:
        with ExitStack() as stack:
            controller = build_cage(cfg, stack)
            if not quiet:
                print(f"characterizing the cage: +-{amplitude_a:g} A, {samples} samples per point")
            model = characterize(controller, amplitude_a, samples=samples, repeats=repeats,
                                 progress=None if quiet else _progress)  # fmt: skip
            version = model.save(cfg.cage.calibration)
    finally:
        for s, h in old.items():
            signal.signal(s, h)  # type: ignore[arg-type]
    if not quiet:
        print("K (uT/A, +- 1 sigma):")
        for row, sig in zip(model.k_ut_per_a, model.k_sigma, strict=True):
            print("  " + "  ".join(f"{v:+9.4f} +-{s:.4f}" for v, s in zip(row, sig, strict=True)))
        print(
            "B0 (uT): "
            + "  ".join(
                f"{v:+8.3f} +-{s:.4f}" for v, s in zip(model.b0_ut, model.b0_sigma_ut, strict=True)
            )
        )
        print(
            f"residual rms {model.meta['residual_rms_nt']:.1f} nT; condition number {model.meta['condition_number']:.2f}"
        )
        print(f"wrote {version} (and {cfg.cage.calibration})")
    return 0


def run_set_field(rig_config: Path, field_ut: list[float], trim: bool, tolerance_nt: float, hold_s: float | None,
                  quiet: bool) -> int:  # fmt: skip
    """Ramp to a field (optionally trimmed on the reference), hold it, then go safe."""
    cfg = load_rig_config(rig_config)
    stop = threading.Event()
    old = _stop_on_signals(stop)
    try:
        with ExitStack() as stack:
            controller = build_cage(cfg, stack)
            target = np.array(field_ut, float)
            if trim:
                result = controller.trim(target, tolerance_nt=tolerance_nt)
                if not quiet:
                    state = "settled" if result.settled else "NOT settled"
                    print(
                        f"trimmed in {result.iterations} iterations: error {result.error_nt:.1f} nT ({state})"
                    )
                if not result.settled:
                    raise RigError(
                        f"the field did not settle within {tolerance_nt:g} nT; check the reference and the cage calibration"
                    )
            else:
                currents = controller.set_field(target)
                if not quiet:
                    print("currents " + ", ".join(f"{c:+.4f} A" for c in currents))
            if not quiet:
                print(
                    f"holding {np.round(target, 3).tolist()} uT "
                    + ("until Ctrl-C" if hold_s is None else f"for {hold_s:g} s")
                )
            stop.wait(hold_s)
    except KeyboardInterrupt:
        if not quiet:
            print("interrupted: outputs ramped down and off")
        return 130
    except DeviceError as exc:
        raise RigError(f"{exc} (outputs were sent to their safe state)") from None
    finally:
        for s, h in old.items():
            signal.signal(s, h)  # type: ignore[arg-type]
    if not quiet:
        print("done: outputs ramped down and off")
    return 0
