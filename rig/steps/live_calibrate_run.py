"""The ``live_calibrate`` step: a sequential filter fed by the samplers while the cage sweeps.

Every settled DUT sample (outside each field or load change and ``settle_s`` after it) is paired
with the newest settled reference sample and the load currents, and updates the filter on a worker
thread of its own (the samplers never wait for it). Twice a second of sample time the physical
1-sigma of each target group is worked out; once every target is met (and ``min_s`` has passed)
the step is told to stop. The history of estimates and sigmas goes to a CSV in the run folder for
the report's convergence plot. When the step's forecast (its plan's sigmas, from the engine:
rig.prediction.live_calibrate_stop) is there, every evaluation also says when the targets will be met
(:func:`rig.calibration.forecast.forecast_stop`): in the status line, on the page, in the CSV.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import timebase
from drivers.transport.tty_watch import tty_seen_stall_s
from rig.analysis import to_cage_frame
from rig.calibration import Samples
from rig.calibration.estimate import delta_method
from rig.calibration.forecast import SigmaForecast, StopForecast, forecast_stop
from rig.calibration.params import Array
from rig.calibration.residuals import p_from_theta, parameter_names
from rig.calibration.result import summarize
from rig.calibration.sequential.guard import DivergenceWatch, check_final
from rig.calibration.sequential.realtime import FilterOptions, filter_estimate, make_filter
from rig.calibration.sequential.zmodel import z_sample
from rig.calibration.targets import group_sigmas, unmet_targets
from rig.errors import CalibrationError

Telemetry = Callable[[float], Array]
CHECK_EVERY_S = 0.5
"""Sample time between two sigma evaluations (and history rows)."""
MAX_PAIRING_S = 0.5
"""Largest time between a DUT sample and the reference sample it is paired with (s)."""
HELD_BACK_MARGIN_S = 0.2
"""A sample that the kernel's terminal layer held back within this long before its time stamp
(s), or since, is not used: its time (dated back from when it arrived) and so its pairing with the
reference, the loads and the field changes is uncertain."""


LIVE_PANEL = "sigma-targets"
"""The live page's panel for a live calibration: each value against its target (app.js)."""


@dataclass
class LiveSnapshot:
    """The latest evaluation: elapsed time (s), updates so far and the sigma of every group."""

    elapsed_s: float = 0.0
    updates: int = 0
    sigmas: dict[str, float] = field(default_factory=dict)


class LiveCalibration:
    """Runs one filter on incoming samples; ``done`` is set when the targets are met."""

    def __init__(
        self,
        params: dict[str, Any],
        noise_ut: float,
        t0: float,
        telemetry: Telemetry,
        correction: dict[str, Any] | None,
    ) -> None:
        self.params = params
        self.channels = tuple(params["telemetry"])
        self.targets: dict[str, float] = dict(params["targets"])
        self.noise_ut = noise_ut
        self.t0 = t0
        self.telemetry = telemetry
        self.correction = correction
        self.names = parameter_names(self.channels, vector=False)
        self.opts = FilterOptions(method=params["method"])
        self.filter = make_filter(self.opts, len(self.channels), noise_ut)
        self.done = timebase.Event()
        self.reason = ""
        self.error: Exception | None = None
        self.snapshot = LiveSnapshot()
        self.history: list[list[float]] = []
        self.forecast: SigmaForecast | None = None
        self.forecast_problem = ""
        self.stop_forecast: StopForecast | None = None
        self.rejected = 0
        self._queue = timebase.Queue()  # (t, DUT, reference, loads), None to end
        self._lock = timebase.Lock()
        self._open_change: float | None = None
        self.quiet_after = t0 + float(params["settle_s"])
        self._reference: tuple[float, Array] | None = None
        self._rows: list[tuple[Array, float, Array, float]] = []
        self._nis: list[float] = []
        self._watch = DivergenceWatch()  # divergence: re-initialized from the batch estimate
        self._recorded: tuple[list[int], list[Array], list[Array]] = ([], [], [])
        self._next_check = t0 + CHECK_EVERY_S
        self._queued = 0  # DUT samples queued for the worker (written by the DUT sampler only)
        self._taken = 0  # ... and finished with by the worker (written by the worker only)
        self._caught_up = timebase.Condition()
        self._thread = timebase.Thread(self._run, name="live-calibration", daemon=True)

    # --- feeds (called from the sampler threads and the runner) ---------------------------------

    def start(self) -> None:
        """Start the worker."""
        self._thread.start()

    def set_forecast(self, forecast: SigmaForecast | None, problem: str = "") -> None:
        """The step's plan forecast (any noise: scaled to the filter's), or why there is none."""
        self.forecast = forecast.scaled(1000.0 * self.noise_ut) if forecast is not None else None
        self.forecast_problem = problem or ("" if forecast else "the plan cannot be forecast")

    def on_dut(self, t: float, xyz: tuple[float, float, float]) -> None:
        """A DUT sample (sampler thread): paired with the reference and the load currents as it
        arrives (so a backlog cannot pair it with a later field), then queued; never blocks."""
        settled, ref = self._state(t)
        if not settled or ref is None or abs(ref[0] - t) > MAX_PAIRING_S or _held_back(t):
            self.rejected += 1
            return
        self._queued += 1
        self._queue.put((t, np.asarray(xyz, float), ref[1], self.telemetry(t)))

    def on_reference(self, t: float, xyz: tuple[float, float, float]) -> None:
        """A reference sample (sampler thread): kept when settled."""
        if self._state(t)[0] and not _held_back(t):
            with self._lock:
                self._reference = (t, np.asarray(xyz, float))

    def change_started(self, t: float) -> None:
        """A field or load change begins at ``t`` (monotonic s)."""
        with self._lock:
            self._open_change = t
            self._reference = None

    def change_ended(self, t: float) -> None:
        """The change is complete at ``t``; samples count again ``settle_s`` later."""
        with self._lock:
            self._open_change = None
            self.quiet_after = t + float(self.params["settle_s"])
            self._reference = None

    def _state(self, t: float) -> tuple[bool, tuple[float, Array] | None]:
        """Whether a sample at ``t`` is settled, and the reference sample kept for it."""
        with self._lock:
            return self._open_change is None and t >= self.quiet_after, self._reference

    # --- the worker -----------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            try:
                if self.error is None:
                    self._update(*item)
            except (CalibrationError, np.linalg.LinAlgError, ValueError) as exc:
                self.error = exc
            finally:
                with self._caught_up:
                    self._taken += 1
                    self._caught_up.notify_all()

    def wait_caught_up(self, timeout_s: float) -> bool:
        """Wait until the worker has finished with every DUT sample queued so far (True), or
        ``timeout_s`` (s) has passed (False): tests feeding samples faster than real time."""
        with self._caught_up:
            return bool(self._caught_up.wait_for(lambda: self._taken >= self._queued, timeout_s))

    def _update(self, t: float, m: Array, ref: Array, u: Array) -> None:
        h_mag = float(np.linalg.norm(to_cage_frame(ref[None, :], self.correction)[0]))
        info = self.filter.update(z_sample(m, h_mag, u), 0.0)
        self._rows.append((m, h_mag, u, t))
        self._nis.append(info.nis if info is not None else math.nan)
        if self._watch.diverged(len(self._rows) - 1, None if info is None else info.nis):
            self._reinitialize()
        if t >= self._next_check:
            self._next_check = t + CHECK_EVERY_S
            self._evaluate(t)

    def _evaluate(self, t: float) -> None:
        if not self.filter.ready:
            return
        n_theta = 9 + 3 * len(self.channels)
        x, big_p, _ = self.filter.final()  # as the result will report it: the data's alone
        theta = np.asarray(x[:n_theta], float)
        cov_theta = np.asarray(big_p[:n_theta, :n_theta], float)
        try:
            p, cov = delta_method(p_from_theta, theta, cov_theta, self.opts.method)
        except CalibrationError:
            return  # not an ellipsoid yet: the next evaluation will tell
        sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        sigmas = group_sigmas(sigma, self.names)
        elapsed = t - self.t0
        self.snapshot = LiveSnapshot(elapsed, len(self._rows), sigmas)
        self.history.append([elapsed, float(len(self._rows)), *p, *sigma,
                             *self._forecast_columns(sigmas, elapsed)])  # fmt: skip
        idx, xs, covs = self._recorded
        idx.append(len(self._rows) - 1)
        xs.append(theta)
        covs.append(cov_theta)
        if (
            self.params["stop_on_target"] == "yes"
            and elapsed >= float(self.params["min_s"])
            and not unmet_targets(sigmas, self.targets)
        ):
            if not self._agrees_with_batch(theta):
                self._reinitialize()  # small sigmas of a wrong answer: not a reason to stop
                return
            self.reason = f"targets met after {elapsed:.1f} s ({len(self._rows)} samples)"
            self.done.set()

    def _forecast_columns(self, sigmas: dict[str, float], elapsed_s: float) -> list[float]:
        """The forecast's sigma of each target group at this many updates and the update
        count it now predicts the targets met at (NaN without a forecast)."""
        f = self.forecast
        groups = list(self.targets)
        if f is None:
            self.stop_forecast = None
            return [math.nan] * (len(groups) + 1)
        self.stop_forecast = forecast_stop(f, sigmas, len(self._rows), elapsed_s, self.targets)
        planned, stop = self.stop_forecast.planned, self.stop_forecast.updates
        return [planned.get(g, math.nan) for g in groups] + [math.nan if stop is None else stop]

    def _samples(self) -> Samples:
        """The settled samples so far, as calibration input."""
        m = np.array([r[0] for r in self._rows])
        h_mag = np.array([r[1] for r in self._rows])
        u = np.array([r[2] for r in self._rows]).reshape(len(self._rows), -1)
        return Samples.build(
            m, field_magnitude_ut=h_mag, telemetry=u if self.channels else None,
            channels=self.channels,
        )  # fmt: skip

    def _reinitialize(self) -> None:
        """Restart the filter from the batch estimate of the samples so far (a divergence)."""
        self._watch.reinitialize(self.filter, self._samples(), len(self._rows) - 1)

    def _agrees_with_batch(self, theta: Array) -> bool:
        """The estimate fits the samples so far about as well as their batch estimate."""
        try:
            check_final(theta, self._samples(), self.noise_ut, self.opts.method, self._watch.report)
        except CalibrationError:
            return False
        return True

    # --- the end --------------------------------------------------------------------------------

    def status(self) -> str:
        """One line for the live view: updates and each group's sigma against its target."""
        snap = self.snapshot
        if snap.updates == 0:
            return f"cal waiting ({self.rejected} samples settling)"
        parts = [f"cal {snap.updates} smp"]
        for key, sigma in snap.sigmas.items():
            limit = self.targets.get(key)
            mark = "" if limit is None else ("ok" if sigma <= limit else f"/{limit:.3g}")
            parts.append(f"{key} {sigma:.3g}{mark}")
        stop = self.stop_forecast
        if stop is not None:
            parts.append("ETA ?" if stop.eta_s is None else f"ETA {stop.eta_s:.0f}s")
        return " ".join(parts)

    def page_state(self) -> dict[str, Any]:
        """For the web page: the panel to draw (:data:`LIVE_PANEL`) with the updates so far,
        each group's 1-sigma and its target."""
        snap = self.snapshot
        panel = {"name": LIVE_PANEL, "updates": snap.updates, "elapsed_s": round(snap.elapsed_s, 2),
                 "values": {k: float(v) for k, v in snap.sigmas.items()},
                 "targets": {k: float(v) for k, v in self.targets.items()}}  # fmt: skip
        stop = self.stop_forecast
        if stop is not None:
            panel["forecast"] = stop.planned
        panel["forecast_line"] = stop.line() if stop is not None else self.forecast_problem
        state: dict[str, Any] = {"panel": panel}
        if stop is not None and stop.eta_s is not None and self.params["stop_on_target"] == "yes":
            # the run's progress and ETA count the step to its forecast stop, not its max_s
            state["step_expected_s"] = max(snap.elapsed_s + stop.eta_s, float(self.params["min_s"]))
        return state

    def stop(self) -> None:
        """Let the worker finish what is queued and end (idempotent)."""
        self._queue.put(None)
        if self._thread.is_alive():
            self._thread.join(timeout=10.0)

    def finish(self, folder: Path, step_name: str, t_end: float) -> dict[str, Any]:
        """Stop the worker, fit the result and write the history CSV; returns the result file
        content with a ``live`` block saying why the step stopped."""
        self.stop()
        if self.error is not None:
            raise CalibrationError(
                f"live calibration '{step_name}' failed: {self.error}; the samples are recorded,"
                " run 'rig calibrate RUN' on them"
            )
        if self._rows:
            self._evaluate(self._rows[-1][3])
        if not self.filter.ready or not self.history:
            raise CalibrationError(
                f"live calibration '{step_name}': the filter never became observable"
                f" ({len(self._rows)} settled samples): lengthen max_s or the dwell"
            )
        data = self._samples()
        n_theta = 9 + 3 * len(self.channels)
        try:  # a filter that still disagrees with the batch fit gives no result
            check_final(np.asarray(self.filter.x[:n_theta], float), data, self.noise_ut,
                        self.opts.method, self._watch.report)  # fmt: skip
        except CalibrationError as exc:
            raise CalibrationError(f"live calibration '{step_name}': {exc}") from None
        est = filter_estimate(
            self.filter, len(self.channels), self.opts, self.noise_ut, np.array(self._nis),
            self._recorded, self._watch.report,
        )  # fmt: skip
        result = summarize(est, data, 1000.0 * self.noise_ut).to_dict()
        history_file = f"live-{_slug(step_name)}.csv"
        with (folder / history_file).open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["elapsed_s", "samples", *self.names, *(f"sigma_{n}" for n in self.names),
                        *(f"forecast_{g}" for g in self.targets), "forecast_stop_updates"])  # fmt: skip
            w.writerows([f"{v:.9g}" for v in row] for row in self.history)
        unmet = unmet_targets(self.snapshot.sigmas, self.targets)
        if not self.reason:
            self.reason = (
                f"max_s ({self.params['max_s']:g} s) reached"
                + (f"; targets not met: {', '.join(unmet)}" if unmet else "; targets met")
                if self.params["stop_on_target"] == "yes"
                else f"ran the full {self.params['max_s']:g} s (stop_on_target: no)"
            )
        result["live"] = {
            "stopped": self.reason,
            "targets_met": not unmet,
            "elapsed_s": t_end - self.t0,
            "updates": len(self._rows),
            "rejected_samples": self.rejected,
            "targets": self.targets,
            "sigma_at_stop": self.snapshot.sigmas,
            "noise_nt": 1000.0 * self.noise_ut,
            "history_file": history_file,
            "forecast": self._forecast_block(),
        }
        return result

    def _forecast_block(self) -> dict[str, Any] | None:
        """What the plan forecast (the stop's update count and dwell, at the filter's noise)
        against what happened; None without a forecast."""
        f = self.forecast
        if f is None:
            return None
        planned = f.first_met(self.targets)
        return {"planned_stop_updates": planned,
                "planned_stop_dwell_s": None if planned is None else f.dwell_at(planned),
                "noise_nt": f.noise_nt}  # fmt: skip


def _held_back(t: float) -> bool:
    """The terminal layer held serial data back around ``t`` (monotonic s) or since."""
    return tty_seen_stall_s(t - HELD_BACK_MARGIN_S) > 0.0


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name.lower()).strip("-") or "step"
