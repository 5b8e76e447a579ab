"""A live terminal view of a running procedure: step, progress with ETA, fields and currents.

It is drawn for a person, on the wall clock, from a thread outside any simulated clock (ADR 0038);
the progress it shows is the run's, on the run's clock (:func:`timebase.monotonic`)."""

from __future__ import annotations

import shutil
import sys
import threading

import numpy as np

import timebase
from rig.engine.page_feed import LiveRun


def _fmt_s(seconds: float) -> str:
    seconds = max(0, int(seconds))
    return f"{seconds // 60}:{seconds % 60:02d}"


class LiveView:
    """Redraws one status line on stderr twice a second (a line per step when not a terminal)."""

    def __init__(self, runner: LiveRun) -> None:
        self.runner = runner
        self.tty = sys.stderr.isatty()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self.durations = [d for _, d in runner.timeline()]
        self.total_s = sum(self.durations)
        self._last_step = -1

    def start(self) -> None:
        """Start redrawing."""
        self._thread.start()

    def line(self) -> str:
        """The status line."""
        r = self.runner
        step = r.tracker.step
        if step is None:
            return "starting"
        idx, name, t0, dur = step.index, step.name, step.t_start, step.duration_s
        done = sum(self.durations[:idx]) + min(max(timebase.monotonic() - t0, 0.0), dur)
        frac = done / self.total_s if self.total_s > 0 else 1.0
        width = 20
        bar = "#" * int(width * frac) + "." * (width - int(width * frac))
        parts = [
            f"[{idx + 1}/{len(self.durations)}] {name[:22]:<22} [{bar}] {100 * frac:3.0f}% ETA {_fmt_s(self.total_s - done)}"
        ]
        ctl = r.cage_controller
        if ctl is not None:
            cmd = ctl.model.field_ut(ctl.currents)
            parts.append("B cmd " + " ".join(f"{v:+6.1f}" for v in cmd))
            ref = r.samplers.get(r.proc.magnetometers.get("reference", ""))
            if ref is not None and ref.latest is not None:
                meas = np.asarray(ref.latest[1])
                parts.append("meas " + " ".join(f"{v:+6.1f}" for v in meas) + " uT")
            parts.append("I " + " ".join(f"{v:+.3f}" for v in ctl.currents) + " A")
        if r.commanded_loads:
            parts.append("loads " + " ".join(f"{k} {v:.2f}A" for k, v in r.commanded_loads.items()))
        for status in list(r.status_sources):  # what the running step has to say
            parts.append(status())
        if r.tracker.pause_requested.is_set():
            parts.append("PAUSED (kill -USR1 to resume)")
        return "  ".join(parts)

    def _run(self) -> None:
        while not self._stop.wait(0.5):
            step = self.runner.tracker.step
            if self.tty:
                cols = shutil.get_terminal_size((120, 20)).columns
                sys.stderr.write("\r" + self.line()[: cols - 1].ljust(cols - 1))
                sys.stderr.flush()
            elif step is not None and step.index != self._last_step:
                self._last_step = step.index
                sys.stderr.write(self.line() + "\n")
                sys.stderr.flush()

    def stop(self) -> None:
        """Stop and end the line."""
        self._stop.set()
        self._thread.join(timeout=1.0)
        if self.tty:
            sys.stderr.write("\n")
            sys.stderr.flush()
