"""What a step kind is: its parameters and checks, how it compiles to commands, how long it takes,
how the engine carries it out, what it adds to the report and which panel the live page draws.

A kind is one module under ``rig/steps/`` defining a :class:`StepKind` subclass, registered in
``rig/steps/__init__.py``. The language, the planner, ``rig check``, the runner, the analysis and
the report find every kind there; none of them names a kind.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np
import numpy.typing as npt

import timebase
from rig.config import coil_step_a
from rig.errors import RunAborted
from rig.steps.load_profiles import load_profile
from rig.steps.vocabulary import (
    ActionCommand,
    Command,
    EndCommand,
    FieldCommand,
    FieldPayload,
    LoadCommand,
    RigTiming,
    Step,
    StepParam,
)
from rig.stored import JsonObject, JsonValue

if TYPE_CHECKING:
    from drivers.protocols import Magnetometer, ScalarMagnetometer
    from rig.cage.controller import CageController
    from rig.calibration.forecast import SigmaForecast
    from rig.config import RigConfig
    from rig.steps.vocabulary import Procedure
    from rig.store.run_store import RunReader

Array = npt.NDArray[np.float64]


class ChangeListener(Protocol):
    """Told when a field or load change begins and ends (monotonic s)."""

    def change_started(self, t: float) -> None: ...

    def change_ended(self, t: float) -> None: ...


class SampledSensor(Protocol):
    """What a step may use of a sensor the run samples (the engine's ``SensorSampler``)."""

    driver: Magnetometer
    listeners: list[Callable[[float, tuple[float, float, float]], None]]
    """Called from the sampling thread with each sample (monotonic s, uT)."""

    def paused(self, timeout_s: float = 2.0) -> AbstractContextManager[Magnetometer]:
        """Sampling held while the caller talks to the driver (e.g. a set/reset pulse)."""
        ...


class RunContext(Protocol):
    """What a step may use of the run carrying it out (the engine's runner provides it)."""

    proc: Procedure
    cfg: RigConfig
    results: dict[str, JsonObject]
    """The steps' results so far, by step name (each as stored)."""
    correction: dict[str, Any] | None  # the reference magnetometer's certificate
    commanded_loads: dict[str, float]  # A
    measured_loads: dict[str, tuple[float, float]]  # device -> (monotonic s, A)
    change_listeners: list[ChangeListener]
    status_sources: list[Callable[[], str]]  # a short text each for the live view
    live_sources: list[Callable[[], JsonObject]]  # values for the web page

    @property
    def folder(self) -> Path:
        """The run folder."""
        ...

    @property
    def controller(self) -> CageController:
        """The cage's controller (the devices are open while a step runs)."""
        ...

    @property
    def samplers(self) -> Mapping[str, SampledSensor]:
        """The sensors this run samples, by device name."""
        ...

    def event(self, level: str, message: str) -> None: ...

    def record_result(self, name: str, value: JsonObject) -> None:
        """Keep step result ``name`` for later steps and in the run's store."""
        ...

    def open_reader(self) -> RunReader:
        """The run's store as recorded so far (flushed); the caller closes it."""
        ...

    def set_meta(self, **values: JsonValue) -> None:
        """Store run metadata (JSON values)."""
        ...

    def scalar_magnetometer(self, name: str) -> ScalarMagnetometer:
        """Total-field magnetometer ``name``, opened for the run and closed with it."""
        ...

    def predict_after_null(self, null_name: str) -> None:
        """From null hold ``null_name``'s result: the calibrations to come predicted again, beside
        the run (rig.prediction.at_null)."""
        ...

    def live_forecast(self, step: Step, noise_nt: float) -> SigmaForecast | None:
        """A live calibration step's sigmas forecast from its plan at the filter's noise
        ``noise_nt`` (nT; rig.prediction.live_calibrate_stop); None when its plan cannot be fitted."""
        ...

    def ask_operator(self, text: str) -> bool: ...

    def command(self, step_index: int, command: FieldCommand | LoadCommand, now: float,
                timing: Mapping[str, float] | None = None) -> None:  # fmt: skip
        """Carry out a field or load set-point now (``now``: when it was issued, monotonic s);
        ``timing`` is recorded with it (the schedule's ``t_due``, monotonic s, and ``t_plan``, s
        from the step's start)."""
        ...

    def request_report(self) -> None: ...


def ask_or_abort(ctx: RunContext, text: str) -> None:
    """Ask the operator ``text``; the answer goes to the run's log, and a "no" aborts the run
    (:class:`~rig.errors.RunAborted`)."""
    ok = ctx.ask_operator(text)
    ctx.event("operator", f"prompt {text!r}: {'confirmed' if ok else 'declined'}")
    if not ok:
        raise RunAborted(f"the operator declined: {text}")


def record_cage_metrology(ctx: RunContext, kind: str, entry: dict[str, Any]) -> str | None:
    """Add a cage metrology result (``kind``: the step kind; ``entry``: what later runs use) to
    the cage calibration record in use: dated, citing this run, saved as a new version of the
    record file when the rig configuration names one (its path returned) and recorded in this
    run's ``cage_model``. Every later run uses and cites it."""
    import datetime as dt

    model = getattr(ctx.controller, "model", None)
    if model is None:
        ctx.event("warning", f"no cage calibration record in use: the {kind} result is not kept")
        return None
    dated = {**entry, "date": dt.datetime.fromtimestamp(timebase.wall_time(), dt.UTC).isoformat(timespec="seconds"),
             "run": ctx.folder.name}  # fmt: skip
    model = model.with_metrology(kind, dated)
    version = None
    cage = ctx.cfg.cage if ctx.cfg is not None else None
    if cage is not None and cage.calibration is not None:
        version = str(model.save(cage.calibration))
        model.meta["file"] = version
    ctx.controller.model = model
    ctx.set_meta(cage_model=model.to_dict())
    return version


class StepExecution:
    """One step being carried out; the runner calls, in order: :meth:`run` for each of the step's
    own commands (between its field and load set-points), :meth:`wind_down` when the commands are
    done or :attr:`stop` was set, then (the step recorded as ended) :meth:`finish`. On any
    exception :meth:`abort` instead. The base class does nothing."""

    stop: threading.Event | None = None
    """Set to end the step's timeline early (a live calibration that met its targets)."""

    def __init__(self, ctx: RunContext, step: Step) -> None:
        self.ctx = ctx
        self.step = step

    def run(self, payload: dict[str, Any]) -> None:
        """The step's own command (kind = the step's kind)."""

    def wind_down(self) -> None:
        """The timeline is over; the step is still open."""

    def finish(self, t_start: float, t_end: float) -> None:
        """The step has ended (monotonic s of its start and end)."""

    def abort(self) -> None:
        """The run is ending with an exception inside this step (before the safe state: quick,
        and talking to no device)."""

    def after_safe(self) -> None:
        """The run ended with an exception inside this step and its outputs are in their safe
        state: put what the step changed on a device back (its samplers and drivers still open).
        An exception here is reported, never in the way of the run's end."""


@dataclass(frozen=True)
class CageAbilities:
    """What the rig's cage can do, as known before a run (``rig check`` and the run's start)."""

    k_ut_per_a: Array | None
    """The cage model's coil matrix (uT/A), None without one."""
    max_slew_a_per_s: float | None
    """The coil supplies' slew limit (A/s), None without a ``[cage]`` section."""
    metrology: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    """The cage record's metrology results by step kind (``cage_response``: its bandwidth)."""
    measured_before: frozenset[str] = frozenset()
    """The metrology kinds a step before this one measures in the same run (the record's older
    result is then not the one the step will meet)."""
    b0_ut: Array | None = None
    """The lab field the coils cancel (uT, cage frame) from a characterization; None when not
    measured (a nominal model: the currents then do not cancel it)."""
    polarity_relays: bool = False
    """The coils change polarity through relays (a flip is a step of the field, and arcs)."""
    coil_tau_s: float | None = None
    """The coils' shortest L/R (s), when the configuration states it (``[cage] coil_tau_s``)."""

    def tracked_slew_a_per_s(self, rate_hz: float) -> float | None:
        """The fastest a coil current may follow set-points sent at ``rate_hz`` (A/s): each
        step into the coil's L/R peaks at the slew limit (:func:`rig.config.coil_step_a`); the
        slew limit itself without an L/R, None without a slew limit."""
        if self.max_slew_a_per_s is None:
            return None
        return coil_step_a(self.max_slew_a_per_s, 1.0 / rate_hz, self.coil_tau_s) * rate_hz


MAX_EXTRA_HOLD_S = 10.0
"""Longest the engine holds a field beyond its planned dwell for its settled samples (s)."""


@dataclass(frozen=True)
class SettledNeed:
    """What each of a step's held fields needs before the next one: ``samples`` settled samples
    (dated whole at least ``settle_s`` s after the field was reached) from each of ``devices``
    (rig configuration device names). The engine holds a field longer until they are in, up to
    :data:`MAX_EXTRA_HOLD_S` (a busy computer delays samples; it must not
    end the run, issue 54)."""

    devices: tuple[str, ...]
    samples: int
    settle_s: float


class StepKind:
    """A kind of procedure step. Subclasses set :attr:`name` and :attr:`params` and override what
    differs from the defaults: one command at time 0 carrying the parameters, no duration."""

    name: ClassVar[str]
    params: ClassVar[dict[str, StepParam]]
    summary: ClassVar[str] = ""
    takes_loads: ClassVar[bool] = False
    """Load profiles may run during it; its samples are in 'every field step' of a calibration."""
    hold_from_field: ClassVar[bool] = False
    """Each field is held for its planned time from when it is reached: the timeline after a field
    command shifts by the time the ramp took (a slow link lengthens the step, never the dwell)."""
    result_values: ClassVar[tuple[str, ...] | None] = None
    """The values its result holds, as dotted paths a ``check`` criterion names (``fnmatch``
    patterns: ``springmann.*``); checked when the procedure is read, so a misspelt value fails
    before the run, not after it. None: not declared (not checked); (): it records no result."""

    def check_against(self, step: Step, earlier: Sequence[Step]) -> None:
        """Refuse (ProcedureError) what ``step`` says about the steps before it (``earlier``),
        when the procedure is read; most kinds say nothing about other steps."""

    asks_operator: ClassVar[bool] = False
    """It asks the operator a question: a run without --yes needs a terminal or the page to answer
    it, checked before the run starts."""
    measures_cage_model: ClassVar[bool] = False
    """It measures the cage model (coil matrix and ambient field) that later steps' currents use:
    a dry run without a characterization cannot know the ambient field those steps cancel."""

    cage_metrology_used: ClassVar[str | None] = None
    """The cage record's metrology result (a step kind: ``cage_response``) this kind is held to
    before a run; ``rig check`` warns when neither the record nor an earlier step has it."""

    def beyond_cage(self, step: Step, cage: CageAbilities) -> list[str]:
        """What ``step`` asks of the cage beyond what it can do (one sentence each, naming the
        fix), checked by ``rig check`` and before a run starts; most kinds ask nothing special."""
        return []

    def shorthand(self, body: Any) -> Any:
        """The step's body as written (``- prompt: "text"``) to its parameter mapping."""
        return body

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        """Checks across parameters; raise ProcedureError naming ``where`` and the fix."""

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        """Nominal duration (s)."""
        return 0.0

    def compile(self, step: Step, base: Path, timing: RigTiming) -> tuple[list[Command], float]:
        """The step's commands (any order; the planner sorts them) and its duration (s)."""
        return [ActionCommand(0.0, self.name, dict(step.params))], self.duration_s(step, timing)

    def field_envelope_ut(self, step: Step) -> float | None:
        """The largest field (uT) the step may ask for in any direction, beyond its planned
        field commands (a closed loop's, known only as it runs); ``rig check`` checks the
        worst direction of each coil against the limits. None: only its commands."""
        return None

    def load_envelope_a(self, step: Step) -> dict[str, float]:
        """The largest current (A) the step may set on each load channel beyond its planned load
        commands (a closed loop's torque rods, known only as it runs); ``rig check`` checks each
        against the channel's limit. Empty: only its commands."""
        return {}

    def peak_coil_current_a(self, step: Step) -> float | None:
        """Coil current (A, every axis) the step drives outside its field commands, if any."""
        return None

    def thermometers(self, step: Step) -> tuple[str, ...]:
        """Thermometers (rig configuration device names) whose recording the step reads: the
        run refuses to start unless each is one the rig records."""
        return ()

    def settled_need(self, step: Step, magnetometers: Mapping[str, str]) -> SettledNeed | None:
        """What each held field of ``step`` needs before the next (``magnetometers``: role to
        device name, the procedure's); None: nothing (the field keeps its planned dwell)."""
        return None

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        """A fresh :class:`StepExecution` for ``step`` in the run ``ctx``."""
        return StepExecution(ctx, step)

    def figures(self, reader: RunReader, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        """(title, matplotlib figure) for the report, from the step's result and recorded data;
        the report lays each out (tight) and draws it once (rig.report.pdf.render_figure)."""
        return []

    def report_lines(self, name: str, result: Any) -> list[str]:
        """Plain-text lines for the report's step results (rendered as HTML, PDF and text; none:
        the report lists the result's numbers)."""
        return []

    def label(self, index: int) -> str:
        """A readable name for a step the procedure did not name (index from 0): what the kind
        does, from its summary."""
        return f"{(self.summary.split(':')[0] or self.name)} (step {index + 1})"


class FieldStepKind(StepKind):
    """A step that sets fields at planned times, with load profiles running meanwhile."""

    takes_loads = True
    hold_from_field = True
    trim_param: ClassVar[str | None] = None
    """A yes/no parameter asking for each field to be trimmed on the reference magnetometer."""

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        """(time offset s, field uT in the cage frame) pairs."""
        raise NotImplementedError

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return len(self.fields(step, timing)) * float(step.params["dwell_s"])

    def field_payload(self, step: Step, field_ut: Array) -> FieldPayload:
        """A ``field`` command's payload."""
        trim = self.trim_param is not None and step.params.get(self.trim_param) == "yes"
        return {"field_ut": [float(v) for v in field_ut], "trim": trim}

    def compile(self, step: Step, base: Path, timing: RigTiming) -> tuple[list[Command], float]:
        duration = self.duration_s(step, timing)
        cmds: list[Command] = [
            FieldCommand(t, self.field_payload(step, f)) for t, f in self.fields(step, timing)
        ]
        cmds += load_commands(step, duration, base)
        cmds.append(EndCommand(duration))
        return cmds, duration


class NullHoldKind(FieldStepKind):
    """A field step that nulls the field and holds it for ``hold_s`` (s): what a kind measuring
    the DUT at rest builds on (noise floor, noise spectrum, offset stability)."""

    trim_param = "trim"

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        return [(0.0, np.zeros(3))]

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return float(step.params["hold_s"])


def load_commands(step: Step, duration_s: float, base: Path) -> list[Command]:
    """The set-points of the step's load profiles, each channel back to 0 A at the end."""
    cmds: list[Command] = []
    for ch, (kind, params) in step.loads.items():
        for t, amps in load_profile(kind, params, duration_s, base):
            cmds.append(LoadCommand(t, {"channel": ch, "current_a": float(amps)}))
        cmds.append(LoadCommand(duration_s, {"channel": ch, "current_a": 0.0}))
    return cmds
