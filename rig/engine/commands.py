"""The run's ``field`` and ``load`` commands: carried out, logged with the time each was issued and
done, and told to the change listeners (a live calibration) as they start and end."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import timebase
from drivers.protocols import Load
from rig.steps.base import ChangeListener
from rig.steps.vocabulary import FieldCommand, FieldPayload, LoadCommand, LoadPayload
from rig.store.run_store import RunWriter


@dataclass
class LoadBook:
    """The run's load channels: what was commanded, what was read back, and when each changed."""

    loads: dict[str, Load] = field(default_factory=dict)
    commanded: dict[str, float] = field(default_factory=dict)  # A
    measured: dict[str, tuple[float, float]] = field(default_factory=dict)  # name -> (time, A)
    changing: dict[str, tuple[float, float]] = field(default_factory=dict)
    """The last change of each: (start, end) monotonic s; end is inf while it is written."""


class Commands:
    """Carries out field and load commands on one run's cage controller and loads."""

    def __init__(self, writer: RunWriter, loads: LoadBook, change_listeners: list[ChangeListener],
                 event: Callable[[str, str], None]) -> None:  # fmt: skip
        self.writer = writer
        self.event = event
        self.loads = loads
        self.change_listeners = change_listeners
        self.controller: Any = None  # the cage controller, once the devices are open

    def command(self, step_idx: int, command: FieldCommand | LoadCommand, now: float,
                timing: Mapping[str, float] | None = None) -> None:  # fmt: skip
        """Carry out a field or load set-point issued at ``now`` (monotonic s) and record it with
        ``timing`` (the schedule's due and plan times); change listeners are told when it starts
        and ends."""
        listeners = list(self.change_listeners)
        for listener in listeners:
            listener.change_started(now)
        record: dict[str, Any] = {**command.payload, **(timing or {})}
        try:
            if isinstance(command, FieldCommand):
                self._set_field(step_idx, command.payload, record, now)
            else:
                self._set_load(step_idx, command.payload, record, now)
        finally:
            for listener in listeners:
                listener.change_ended(timebase.monotonic())

    def _set_field(self, step_idx: int, payload: FieldPayload, record: dict[str, Any],
                   now: float) -> None:  # fmt: skip
        w = self.writer
        target = np.array(payload["field_ut"])
        if payload.get("track"):
            # One tracked set-point moves the field by a slew-limited step that the reference
            # follows (interpolated): no interval to leave out (rig.analysis.change_times). A
            # ramp through zero is one. Its window (issued .. done) is when the axes were written.
            ramped = self.controller.track(target)
            record["ramped"] = ramped
        elif payload.get("trim"):
            result = self.controller.trim(target)
            if not result.settled:
                self.event("warning", f"trim did not settle: {result.error_nt:.1f} nT")
        else:
            self.controller.set_field(target)
        # Logged when the ramp has finished: analysis counts settling from here.
        done = timebase.monotonic()
        w.add_command(done, step_idx, "field", record | {"t_issued": min(now, done)})
        for ax, amps in enumerate(self.controller.currents):
            w.add_channel(timebase.monotonic(), f"coil_{'xyz'[ax]}", float(amps), None)

    def _set_load(self, step_idx: int, payload: LoadPayload, record: dict[str, Any],
                  now: float) -> None:  # fmt: skip
        w, book = self.writer, self.loads
        name, amps = payload["channel"], float(payload["current_a"])
        book.changing[name] = (now, math.inf)
        try:
            book.loads[name].set_current(amps)
        finally:
            done = (
                timebase.monotonic()
            )  # logged once written, like a field: settling counts from here
            book.changing[name] = (now, done)
        book.commanded[name] = amps
        w.add_command(done, step_idx, "load", record | {"t_issued": min(now, done)})
        w.add_channel(done, name, amps, None)
