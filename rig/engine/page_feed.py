"""The run's side of the web page: publish the live state, carry out the page's requests.

A thread of its own (the steps never wait for it) writes ``live.json`` in the run folder twice a
second and looks for requests in ``control/`` ten times a second (:mod:`rig.store.run_control`):
pause, resume and abort go through the same events as the signals and Ctrl-C, and an answer to an
operator prompt is handed to :meth:`Runner.ask_operator`, which takes the page's or the
terminal's, whichever comes first. It creates ``control/`` (0700) as the run starts and takes only
its owner's requests; any other is ignored and recorded once as a warning event.

Clocks (ADR 0038): the thread serves the page, a reader in the real world, so it paces itself on
the wall clock and, in simulated time, stays outside the simulated clock (it may set the run's
events, never wait on them). The times it publishes are the run's (:func:`timebase.monotonic`);
``wall_time`` says when the file was written. A page's answer rings :attr:`LivePublisher.answered`,
which the operator's prompt waits on in the run's time.
"""

from __future__ import annotations

import collections
import contextlib
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

import timebase
from rig.analysis import apply_correction
from rig.calibration.record import latest_calibration
from rig.engine.run_tracker import RunTracker
from rig.procedure.language import Procedure
from rig.store.run_control import CONTROL_DIR, open_box, take_requests, write_live
from rig.store.run_states import RunStatus
from rig.stored import JsonObject

if TYPE_CHECKING:
    from rig.cage.controller import CageController
    from rig.engine.sampling import SensorSampler

POLL_S = 0.1
"""How often the requests are looked for (s): an abort reaches the safe path within this."""
PUBLISH_S = 0.5
"""How often ``live.json`` is replaced (s)."""
EVENTS_KEPT = 50


def _vec(v: Any) -> list[float] | None:
    if v is None:
        return None
    return [round(float(x), 4) for x in np.asarray(v, dtype=float).reshape(-1)]


def corrected_dut(run: LiveRun, raw_ut: npt.ArrayLike | None) -> npt.NDArray[np.float64] | None:
    """The DUT reading ``raw_ut`` (uT) corrected by the newest calibration the run has fitted
    (``latest_calibration``; loads at their commanded currents), None before the first one."""
    latest = latest_calibration(run.results) if raw_ut is not None else None
    if latest is None:
        return None
    corr = latest[1].correction
    channels = list(corr.get("k_ut_per_unit", {}))
    loads = np.array([[run.commanded_loads.get(ch, 0.0) for ch in channels]])
    rows = apply_correction(corr, np.asarray(raw_ut, float)[None, :], loads, channels)
    return np.asarray(rows[0], dtype=np.float64)


class LiveRun(Protocol):
    """What the live view and the page read of a run (the engine's runner)."""

    tracker: RunTracker
    proc: Procedure
    cage_controller: CageController | None  # once the devices are open
    samplers: dict[str, SensorSampler]  # by sampled device name
    results: dict[str, JsonObject]  # the steps' results so far
    commanded_loads: dict[str, float]
    measured_loads: dict[str, tuple[float, float]]
    status_sources: list[Callable[[], str]]
    live_sources: list[Callable[[], JsonObject]]

    @property
    def folder(self) -> Path: ...

    def timeline(self) -> list[tuple[str, float]]: ...

    def event(self, level: str, message: str) -> None: ...

    def abort_from(self, reason: str) -> None: ...


class LivePublisher:
    """Publishes ``runner``'s state and applies the page's requests until :meth:`stop`."""

    def __init__(self, runner: LiveRun, timeline: list[tuple[str, float]]) -> None:
        self.runner = runner
        self.timeline = timeline
        self.events: collections.deque[tuple[float, str, str]] = collections.deque(
            maxlen=EVENTS_KEPT
        )
        self.final: dict[str, Any] | None = None
        self.prompt: tuple[int, str] | None = None
        self.answers: dict[int, bool] = {}
        self._prompts = 0
        # taken by the page's thread and the run's, never across a wait: a plain lock
        self._lock = threading.Lock()
        self.answered = timebase.Event()
        """Rung when the page answers a prompt (the thread may ring it from outside the clock)."""
        self._stop = threading.Event()
        self._t_start = timebase.monotonic()
        self._thread = threading.Thread(target=self._run, name="live-state", daemon=True)
        self.publish_errors = 0
        self.refused: set[str] = set()
        """Lines already recorded about requests that were ignored (each is recorded once)."""

    def start(self) -> None:
        """Start publishing."""
        with contextlib.suppress(OSError):  # no request box: the page cannot operate, that is all
            open_box(self.runner.folder)
        self._publish()
        self._thread.start()

    def stop(self, status: str, reason: str) -> None:
        """Publish the final state (``status``, ``reason``) and end the thread."""
        self.final = {"status": status, "reason": reason}
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._publish()
        with contextlib.suppress(OSError):  # an empty request box is not kept with the data
            (self.runner.folder / CONTROL_DIR).rmdir()

    def note_event(self, t: float, level: str, message: str) -> None:
        """Keep an event for the page (the store has them all)."""
        self.events.append((t, level, message))

    # --- operator prompts -------------------------------------------------------------------------

    def open_prompt(self, text: str) -> int:
        """Show ``text`` on the page as a yes/no question; returns its number."""
        with self._lock:
            self._prompts += 1
            self.prompt = (self._prompts, text)
            return self._prompts

    def close_prompt(self) -> None:
        """The question is answered (here or on the terminal): take it off the page."""
        with self._lock:
            self.prompt = None

    def wait_answer(self, prompt_id: int, timeout_s: float) -> bool | None:
        """The page's answer to prompt ``prompt_id`` if it comes within ``timeout_s`` (s on the
        run's clock), else None."""
        with self._lock:
            waiting = prompt_id not in self.answers
            if waiting:
                self.answered.clear()
        if waiting:
            self.answered.wait(timeout_s)
        with self._lock:
            return self.answers.pop(prompt_id, None)

    # --- the thread -------------------------------------------------------------------------------

    def _run(self) -> None:
        next_publish = time.monotonic() + PUBLISH_S
        while not self._stop.wait(POLL_S):
            refused: list[str] = []
            self._apply(take_requests(self.runner.folder, refused))
            for line in dict.fromkeys(refused):
                if line not in self.refused:
                    self.refused.add(line)
                    self.runner.event("warning", line)
            if time.monotonic() >= next_publish:
                next_publish = time.monotonic() + PUBLISH_S
                self._publish()

    def _apply(self, requests: list[dict[str, Any]]) -> None:
        r = self.runner
        for req in requests:
            action = req["action"]
            if action == "abort":
                r.abort_from("aborted from the web page")
            elif action == "pause":
                r.tracker.pause_requested.set()
            elif action == "resume":
                r.tracker.pause_requested.clear()
            elif action == "answer":
                with self._lock:
                    current = self.prompt
                    if current is not None and current[0] == req.get("prompt"):
                        self.answers[current[0]] = bool(req.get("yes"))
                        self.answered.set()

    def _publish(self) -> None:
        try:
            write_live(self.runner.folder, self.snapshot())
        except Exception:  # a full disk or a vanished folder must not end the run from here
            self.publish_errors += 1

    def snapshot(self) -> dict[str, Any]:
        """The state the page shows (JSON-ready; vectors in uT, currents in A, times in s)."""
        r = self.runner
        now = timebase.monotonic()
        state: dict[str, Any] = {
            "t": round(now - self._t_start, 3),
            "wall_time": time.time(),
            "status": RunStatus.RUNNING,
            "paused": r.tracker.holding,
            "pause_requested": r.tracker.pause_requested.is_set(),
            "steps": [{"name": n, "duration_s": round(d, 3)} for n, d in self.timeline],
        }
        ctl = r.cage_controller
        if ctl is not None:
            state["field_cmd_ut"] = _vec(ctl.model.field_ut(ctl.currents))
            state["coil_a"] = _vec(ctl.currents)
        for role in ("reference", "dut"):
            sampler = r.samplers.get(r.proc.magnetometers.get(role, ""))
            latest = sampler.latest if sampler is not None else None
            if latest is not None:
                state[f"{role}_ut"] = _vec(latest[1])
        corrected = corrected_dut(r, state.get("dut_ut"))
        if corrected is not None:
            state["dut_corrected_ut"] = _vec(corrected)
        state["loads_cmd_a"] = {k: round(float(v), 4) for k, v in r.commanded_loads.items()}
        state["loads_a"] = {k: round(float(v[1]), 4) for k, v in list(r.measured_loads.items())}
        for source in list(r.live_sources):
            try:
                state |= source()
            except Exception:  # a step's view must not stop the page
                continue
        step = r.tracker.step
        expected = state.pop("step_expected_s", None)  # a step that knows when it will end
        if step is not None:
            idx, name, t0, dur = step.index, step.name, step.t_start, step.duration_s
            if isinstance(expected, int | float) and 0.0 <= expected < dur:
                dur = float(expected)
            done = sum(d for _, d in self.timeline[:idx]) + min(max(now - t0, 0.0), dur)
            total = sum(d for _, d in self.timeline) - step.duration_s + dur
            state["step"] = {"index": idx, "name": name, "elapsed_s": round(now - t0, 3),
                             "duration_s": dur}  # fmt: skip
            state["progress"] = round(done / total, 4) if total > 0 else 1.0
            state["eta_s"] = round(max(total - done, 0.0), 1)
        with self._lock:
            if self.prompt is not None:
                state["prompt"] = {"id": self.prompt[0], "text": self.prompt[1]}
        state["events"] = [{"t": round(t - self._t_start, 2), "level": lv, "message": m}
                           for t, lv, m in list(self.events)]  # fmt: skip
        if self.final is not None:
            state |= self.final
        return state
