"""A fake :class:`rig.steps.base.RunContext` for unit tests of step kinds: no simulator, no store.

The run's recorded data are a :class:`Recording` the test fills with synthetic samples and
commands; :meth:`FakeContext.open_reader` reads it through the read methods of
:class:`rig.store.run_store.RunReader` that the analysis uses. Commands, events, questions and
results are kept in lists and dicts for the test to look at.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from rig.steps import KINDS
from rig.steps.base import ChangeListener, StepExecution
from rig.steps.vocabulary import (
    ActionCommand,
    Command,
    FieldCommand,
    LoadCommand,
    Procedure,
    RigTiming,
    Step,
    Where,
    bind_params,
)

Array = npt.NDArray[np.float64]
WHERE = "test.yaml:1: step 1"


def make_step(
    kind: str,
    body: Any = None,
    *,
    loads: tuple[str, ...] = (),
    index: int = 0,
    name: str | None = None,
    step_loads: dict[str, tuple[str, dict[str, Any]]] | None = None,
) -> Step:
    """A validated step of ``kind`` as the language makes it: ``body`` (as written under the
    kind's name) bound to its parameters, defaults filled in, and checked by its ``validate``."""
    k = KINDS[kind]
    where = f"{WHERE} ({kind})"
    params = bind_params(k.params, k.shorthand(body if body is not None else {}), where, kind)
    k.validate(params, loads, where)
    return Step(
        index,
        kind,
        name or f"{kind} {index + 1}",
        params,
        step_loads or {},
        Where("test.yaml", 1),
    )


def make_procedure(
    *steps: Step, magnetometers: dict[str, str] | None = None, loads: tuple[str, ...] = ()
) -> Procedure:
    """A procedure of ``steps`` (default roles: dut and reference, devices of the same names)."""
    mags = magnetometers if magnetometers is not None else {"dut": "dut", "reference": "reference"}
    return Procedure("Test", Path("test.yaml"), {}, mags, loads, steps)


def compile_step(step: Step, timing: RigTiming | None = None) -> tuple[list[Command], float]:
    """The step's commands, time-ordered as the planner sorts them, and its duration (s)."""
    cmds, duration = KINDS[step.kind].compile(step, Path("."), timing or RigTiming())
    return sorted(cmds, key=lambda c: c.t_s), duration


@dataclass
class Recording:
    """What a run has recorded so far, in the shapes :class:`RunReader` returns."""

    samples: dict[str, list[tuple[float, float, float, float]]] = field(default_factory=dict)
    commands: list[tuple[float, int | None, str, dict[str, Any]]] = field(default_factory=list)
    steps: list[tuple[int, str, str, float, float | None]] = field(default_factory=list)
    channels: dict[str, list[tuple[float, float | None, float | None]]] = field(
        default_factory=dict
    )
    meta: dict[str, Any] = field(default_factory=dict)

    def add_samples(self, device: str, t_s: Array, xyz_ut: Array) -> None:
        """Readings (N, 3) uT of ``device`` at times ``t_s`` (s)."""
        rows = self.samples.setdefault(device, [])
        rows += [
            (float(t), float(x), float(y), float(z))
            for t, (x, y, z) in zip(t_s, xyz_ut, strict=True)
        ]
        rows.sort()

    def add_field(self, t_s: float, field_ut: Iterable[float], step: int = 0) -> None:
        """A field command done at ``t_s`` (issued then too: an instant ramp)."""
        payload = {"field_ut": [float(v) for v in field_ut], "t_issued": t_s}
        self.commands.append((t_s, step, "field", payload))
        self.commands.sort(key=lambda c: c[0])


def held_fields(
    recording: Recording,
    fields_ut: Array,
    dwell_s: float,
    dut: Callable[[Array], Array],
    *,
    t0: float = 100.0,
    ref_hz: float = 20.0,
    dut_hz: float = 10.0,
    noise_ut: float = 0.0,
    seed: int = 0,
    step: tuple[int, str, str] = (0, "sweep", "sphere_sweep"),
) -> tuple[float, float]:
    """Record ``fields_ut`` (N, 3) each held ``dwell_s`` from ``t0``: a field command at each
    start, the reference reading the field and the DUT reading ``dut(field)`` (both plus white
    noise of ``noise_ut`` per axis) at their rates, and the step's window. Returns the window."""
    rng = np.random.default_rng(seed)
    t1 = t0 + len(fields_ut) * dwell_s
    for i, f in enumerate(fields_ut):
        recording.add_field(t0 + i * dwell_s, f, step[0])
    for device, rate, reading in (("reference", ref_hz, lambda b: b), ("dut", dut_hz, dut)):
        t = np.arange(t0 + 0.5 / rate, t1, 1.0 / rate)
        idx = np.minimum(((t - t0) // dwell_s).astype(int), len(fields_ut) - 1)
        clean = reading(np.asarray(fields_ut, float)[idx])
        recording.add_samples(device, t, clean + noise_ut * rng.standard_normal(clean.shape))
    recording.steps.append((*step, t0, t1))
    return t0, t1


class FakeReader:
    """The read side of a run over a :class:`Recording` (RunReader's methods the steps use)."""

    def __init__(self, recording: Recording) -> None:
        self.rec = recording
        self.closed = False

    def meta(self) -> dict[str, Any]:
        return dict(self.rec.meta)

    def samples(self, device: str) -> list[tuple[float, float, float, float]]:
        return list(self.rec.samples.get(device, []))

    def dated_samples(self, device: str) -> list[tuple[float, float, float, float, float]]:
        """(t, x, y, z, t_unc): synthetic samples are dated exactly (1 ms, the floor a stream
        clock claims)."""
        return [(*row, 0.001) for row in self.rec.samples.get(device, [])]

    def devices(self) -> list[str]:
        return sorted(d for d, rows in self.rec.samples.items() if rows)

    def channel(self, name: str) -> list[tuple[float, float | None, float | None]]:
        return sorted(self.rec.channels.get(name, []), key=lambda r: r[0])

    def channel_column(
        self, name: str, column: Literal["commanded", "measured"]
    ) -> list[tuple[float, float]]:
        i = 1 if column == "commanded" else 2
        return [(r[0], v) for r in self.channel(name) if (v := r[i]) is not None]

    def channel_names(self) -> list[str]:
        return sorted(self.rec.channels)

    def commands(self) -> list[tuple[float, int | None, str, dict[str, Any]]]:
        return sorted(self.rec.commands, key=lambda c: c[0])

    def steps(self) -> list[tuple[int, str, str, float, float | None]]:
        return sorted(self.rec.steps)

    def close(self) -> None:
        self.closed = True


@dataclass
class FakeSampler:
    """A sampler as a step sees it: a list of ``(t, xyz)`` listeners."""

    listeners: list[Callable[[float, tuple[float, float, float]], None]] = field(
        default_factory=list
    )


@dataclass
class FakeContext:
    """A :class:`rig.steps.base.RunContext` that records what a step does with it."""

    proc: Procedure
    folder: Path
    recording: Recording = field(default_factory=Recording)
    cfg: Any = None
    controller: Any = None
    results: dict[str, Any] = field(default_factory=dict)
    correction: dict[str, Any] | None = None
    samplers: dict[str, Any] = field(default_factory=dict)
    commanded_loads: dict[str, float] = field(default_factory=dict)
    measured_loads: dict[str, tuple[float, float]] = field(default_factory=dict)
    change_listeners: list[ChangeListener] = field(default_factory=list)
    status_sources: list[Any] = field(default_factory=list)
    live_sources: list[Any] = field(default_factory=list)
    answer: bool = True
    """What the operator answers every question."""
    events: list[tuple[str, str]] = field(default_factory=list)
    sent: list[tuple[int, str, dict[str, Any]]] = field(default_factory=list)
    """``field`` and ``load`` commands the step gave (step index, kind, payload)."""
    questions: list[str] = field(default_factory=list)
    meta: dict[str, Any] = field(default_factory=dict)
    report_requested: bool = False
    readers: list[FakeReader] = field(default_factory=list)
    scalars: dict[str, Any] = field(default_factory=dict)
    forecast: Any = None  # a live step's SigmaForecast (rig.calibration.forecast), if any
    null_holds: list[str] = field(default_factory=list)
    """The null holds whose prediction update a step asked for (predict_after_null)."""
    """Total-field magnetometers by name (what :meth:`scalar_magnetometer` opens)."""

    def __post_init__(self) -> None:
        if not self.samplers:
            self.samplers = {dev: FakeSampler() for dev in self.proc.magnetometers.values()}

    def event(self, level: str, message: str) -> None:
        self.events.append((level, message))

    def record_result(self, name: str, value: Any) -> None:
        self.results[name] = value

    def open_reader(self) -> Any:
        reader = FakeReader(self.recording)
        self.readers.append(reader)
        return reader

    def set_meta(self, **values: Any) -> None:
        self.meta.update(values)

    def scalar_magnetometer(self, name: str) -> Any:
        return self.scalars[name]

    def predict_after_null(self, null_name: str) -> None:
        self.null_holds.append(null_name)

    def live_forecast(self, step: Any, noise_nt: float) -> Any:
        return self.forecast.scaled(noise_nt) if self.forecast is not None else None

    def ask_operator(self, text: str) -> bool:
        self.questions.append(text)
        return self.answer

    def command(self, step_index: int, command: FieldCommand | LoadCommand, now: float,
                timing: Mapping[str, float] | None = None) -> None:  # fmt: skip
        self.sent.append((step_index, command.kind, dict(command.payload)))

    def request_report(self) -> None:
        self.report_requested = True


def carry_out(ctx: FakeContext, step: Step, window: tuple[float, float] = (0.0, 1.0)) -> Any:
    """Carry ``step`` out as the runner does, minus the field and load commands (the runner's
    own): its kind's commands to ``run``, then ``wind_down`` and ``finish(window)``. Returns the
    step's result (None if it recorded none), having checked it closed every reader it opened."""
    execution: StepExecution = KINDS[step.kind].execution(ctx, step)
    try:
        for cmd in compile_step(step)[0]:
            if isinstance(cmd, ActionCommand) and cmd.kind == step.kind:
                execution.run(cmd.payload)
        execution.wind_down()
        execution.finish(*window)
    except BaseException:
        execution.abort()
        raise
    assert all(r.closed for r in ctx.readers), "the step left a reader open"
    return ctx.results.get(step.name)
