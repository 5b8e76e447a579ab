"""``closed_loop``: hardware in the loop (ADR 0043). A spacecraft whose attitude Basilisk
propagates; every tick the field in its body frame (IGRF along the TLE's orbit, turned by the
attitude) is made by the cage through the same limits and tracking as any field; every control
period the DUT's readings of it (raw, or corrected by the run's latest calibration) go to the
flight software under test (B-dot), whose dipole commands turn the spacecraft. Afterwards the
same scenario runs all in software (a model magnetometer with the DUT's measured noise) and the
two are compared: the difference is what the hardware changed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import timebase
from rig.errors import RigError, UserInputError
from rig.steps.base import Array, FieldStepKind, RunContext, StepExecution
from rig.steps.closed_loop_run import LoopRunner, scenario_of
from rig.steps.closed_loop_ticks import read_ticks
from rig.steps.vocabulary import (
    MAX_FIELD_SETPOINTS_PER_STEP,
    ActionCommand,
    Command,
    EndCommand,
    FieldCommand,
    LoadCommand,
    ProcedureError,
    RigTiming,
    Step,
    StepParam,
)

ABORT_JOIN_S = 10.0
"""Longest wait for the loop's command in flight when the run aborts (s): a Modbus write with its
retries."""


class ClosedLoop(FieldStepKind):
    name = "closed_loop"
    summary = (
        "close the loop: Basilisk's spacecraft, the cage's field, the DUT, B-dot flight software"
    )
    takes_loads = False  # the loop owns the step's time; load profiles would race its commands
    result_values = ("detumble_s", "software_detumble_s", "difference_pct", "final_rate_deg_s",
                     "ticks", "late_ticks", "latency_ms.*", "readings", "field_model", "dynamics",
                     "history_file", "software_history_file", "noise_nt", "peak_field_ut",
                     "until_deg_s", "summary", "flight_software", "flight_computer.*", "torque_rods.*")  # fmt: skip
    params: ClassVar[dict[str, StepParam]] = {
        "tle": StepParam("list_str", required=True),
        "start": StepParam("str", required=True),
        "time_scale": StepParam("float", 1.0, 0.01, 1000.0),
        "duration_s": StepParam("float", required=True, minimum=1.0, maximum=86400.0),
        "rate_hz": StepParam("float", 50.0, 1.0, 200.0),
        "control_hz": StepParam("float", 2.0, 0.05, 50.0),
        "inertia_kg_m2": StepParam("vec3", [0.0333, 0.0333, 0.0067], 1e-6, 1e4),
        "max_dipole_am2": StepParam("float", 0.2, 1e-4, 100.0),
        "rate_deg_s": StepParam("vec3", [5.77, 5.77, 5.77], -360.0, 360.0),
        "gain": StepParam("float", 0.0, 0.0, 1e6),
        "until_deg_s": StepParam("float", 0.0, 0.0, 360.0),
        "readings": StepParam("str", "raw", choices=("raw", "calibrated")),
        "field_scale": StepParam("float", 1.0, 0.05, 1.0),
        "noise_nt": StepParam("float", 0.0, 0.0, 1e6),
        "seed": StepParam("int", 0, 0, 2**31),
        "magnetometer": StepParam("str", "dut"),
        "flight_computer": StepParam("str", ""),
        "reply_timeout_s": StepParam("float", 0.1, 0.001, 10.0),
        "torque_rods": StepParam("list_str", []),
        "rod_a_per_am2": StepParam("float", 0.0, 0.0, 1000.0),
        "rod_bias_a": StepParam("float", 0.0, 0.0, 1000.0),
    }
    """``inertia_kg_m2``: the principal moments (body axes = cage axes); ``rate_deg_s``: the
    initial body rate; ``gain``: B-dot's (A m^2 per uT/s; 0: full dipole at 1 deg/s in 30 uT);
    ``until_deg_s``: the body rate at which the spacecraft counts as detumbled and the step ends
    (0: it runs ``duration_s``); ``time_scale``: orbit seconds per second of the loop (the orbit's
    field turns faster than in orbit, the attitude at its own pace); ``noise_nt``: the
    all-software run's magnetometer noise (0: the DUT's from the run's latest null field);
    ``flight_computer``: an external one at ``udp://HOST:PORT`` or
    ``serial:///dev/PORT[?baud=N]`` (docs/hil.md's protocol; its answer awaited
    ``reply_timeout_s``), empty for the in-process B-dot; ``torque_rods``: the
    load channels of the x, y and z rods (``none`` for an axis without one), each carrying
    ``rod_bias_a + dipole * rod_a_per_am2`` (A) so that its stray field reaches the DUT
    (rig.hil.torque_rods)."""

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        from rig.steps.orbit import validate_orbit

        problem = validate_orbit(params, where, MAX_FIELD_SETPOINTS_PER_STEP)
        if problem is not None:
            raise ProcedureError(problem)
        if params["flight_computer"]:
            from rig.hil.flight_links import parse_address

            try:
                parse_address(params["flight_computer"])
            except UserInputError as exc:
                raise ProcedureError(f"{where}: {exc}") from None
        from rig.hil.torque_rods import rods_problem

        rods = rods_problem(params, loads)
        if rods is not None:
            raise ProcedureError(f"{where}: {rods}")
        if params["control_hz"] > params["rate_hz"]:
            raise ProcedureError(f"{where}: control_hz must not exceed rate_hz (the tick rate)")
        if min(params["inertia_kg_m2"]) <= 0:
            raise ProcedureError(f"{where}: every principal moment of inertia must be > 0")
        if max(abs(v) for v in params["rate_deg_s"]) > 360.0:
            raise ProcedureError(f"{where}: 'rate_deg_s' must be at most 360 deg/s on each axis")

    def duration_s(self, step: Step, timing: RigTiming) -> float:
        return float(step.params["duration_s"])

    def fields(self, step: Step, timing: RigTiming) -> list[tuple[float, Array]]:
        """The field at the start: the initial attitude in the orbit's field at its start."""
        return [(0.0, scenario_of(step.params).initial_field_ut())]

    def field_envelope_ut(self, step: Step) -> float | None:
        """Any direction in the body may see the orbit's largest field (uT, scaled)."""
        return scenario_of(step.params).peak_field_ut()

    def load_envelope_a(self, step: Step) -> dict[str, float]:
        """Each rod's load at the rod's largest dipole (A)."""
        rods = scenario_of(step.params).rods
        return {} if rods is None else rods.peak_a(float(step.params["max_dipole_am2"]))

    def compile(self, step: Step, base: Path, timing: RigTiming) -> tuple[list[Command], float]:
        """The starting field (ramped there and settled), the loop itself, its end."""
        try:
            start = self.fields(step, timing)[0][1]
        except ValueError as exc:
            raise ProcedureError(
                f"{step.where}: step {step.index + 1} (closed_loop): {exc}"
            ) from None
        duration = self.duration_s(step, timing)
        rods = scenario_of(step.params).rods
        at_rest = [] if rods is None else [
            LoadCommand(0.0, {"channel": ch, "current_a": amps})
            for ch, amps in rods.currents_a((0.0, 0.0, 0.0)).items()]  # fmt: skip
        return [FieldCommand(0.0, self.field_payload(step, start)), *at_rest,
                ActionCommand(0.0, self.name, {}), EndCommand(duration)], duration  # fmt: skip

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return ClosedLoopStep(ctx, step)

    def report_lines(self, name: str, result: Any) -> list[str]:
        """The comparison the step exists for, in words: the detumble through the cage against
        all in software, what the loop ran on, how late it ran, the rods and the link."""
        if not isinstance(result, dict):
            return []
        r = result
        lines = [
            _detumble_line(r),
            f"Flight software: {r.get('flight_software', '-')}; the DUT's readings"
            f" {r.get('readings', '-')}; field: {r.get('field_model', '-')}; dynamics:"
            f" {r.get('dynamics', '-')}.",
        ]
        latency = r.get("latency_ms") or {}
        lines.append(
            f"Loop: {r.get('ticks', 0)} ticks, {r.get('late_ticks', 0)} late (a command more than"
            f" a period after it was due); latency from the newest DUT reading to the command it"
            f" moved: p50 {latency.get('p50', float('nan')):.0f} ms, p99"
            f" {latency.get('p99', float('nan')):.0f} ms, max {latency.get('max', float('nan')):.0f} ms."
        )  # fmt: skip
        rods = r.get("torque_rods")
        if isinstance(rods, dict):
            lines.append(
                f"Torque rods on loads {', '.join(str(c) for c in rods.get('channels', []))}"
                f" (x, y, z): {rods.get('bias_a', 0):g} A + {rods.get('a_per_am2', 0):g} A per A m^2;"
                f" their currents changed {rods.get('changes', 0)} times."
            )  # fmt: skip
        link = r.get("flight_computer")
        if isinstance(link, dict):
            first = f" (first: {link.get('problem')})" if link.get("missed") else ""
            trip = float(link.get("round_trip_ms_p99") or float("nan"))
            lines.append(f"Flight computer link: {link.get('answered', 0)} answers,"
                         f" {link.get('missed', 0)} missed{first}; round trip p99 {trip:.1f} ms.")  # fmt: skip
        return lines

    def figures(self, reader: Any, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        """The body rate and the dipoles against time, through the cage and all in software."""
        folder = getattr(reader, "folder", None)
        if not isinstance(result, dict) or folder is None:
            return []
        runs = [(label, read_ticks(folder, result.get(key)))
                for label, key in (("through the cage", "history_file"),
                                   ("all software", "software_history_file"))]  # fmt: skip
        if any(ticks is None for _, ticks in runs):
            return []
        fig, (rate_ax, dipole_ax) = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
        for (label, ticks), style in zip(runs, ("-", "--"), strict=True):
            assert ticks is not None
            rate_ax.plot(ticks["t_s"], ticks["rate_deg_s"], style, lw=1.0, label=label)
            dipole_ax.plot(ticks["t_s"], ticks["dipole_am2"], style, lw=0.8, label=label)
        until = float(result.get("until_deg_s") or 0.0)
        if until > 0:
            rate_ax.axhline(until, color="k", ls=":", lw=0.8, label="detumbled below")
        rate_ax.set_ylabel("body rate (deg/s)")
        dipole_ax.set_ylabel("|dipole| (A m^2)")
        dipole_ax.set_xlabel("time in step (s)")
        for ax in (rate_ax, dipole_ax):
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper right")
        return [
            (
                f"Closed loop '{name}': body rate and dipoles, through the cage and all in software",
                fig,
            )
        ]


class ClosedLoopStep(StepExecution):
    """The loop on its own thread from the step's command until detumbled, out of time or the
    step ends; then the all-software run and the comparison, recorded as the step's result."""

    def __init__(self, ctx: RunContext, step: Step) -> None:
        super().__init__(ctx, step)
        role = step.params["magnetometer"]
        dut = ctx.proc.magnetometers.get(role, role)
        if dut not in ctx.samplers:
            raise RigError(
                f"{ctx.proc.path}: closed_loop needs the '{role}' magnetometer under"
                " 'magnetometers' (its readings go to the flight software)"
            )
        self.runner = LoopRunner(ctx, step, dut)
        self.stop = self.runner.detumbled
        ctx.samplers[dut].listeners.append(self.runner.on_sample)
        ctx.status_sources.append(self.runner.status)
        self._dut = dut
        self._thread: Any = None

    def run(self, payload: dict[str, Any]) -> None:
        """The step's command: the loop starts (the starting field is made and settled)."""
        self._thread = timebase.Thread(self.runner.run, name="closed-loop", daemon=True)
        self._thread.start()

    def _detach(self) -> None:
        listeners = self.ctx.samplers[self._dut].listeners
        if self.runner.on_sample in listeners:
            listeners.remove(self.runner.on_sample)
        if self.runner.status in self.ctx.status_sources:
            self.ctx.status_sources.remove(self.runner.status)

    def wind_down(self) -> None:
        """The step's time is over, or the spacecraft detumbled: the loop ends."""
        self.runner.halt()
        if self._thread is not None:
            self._thread.join()
        self._detach()
        if self.runner.error is not None:
            raise self.runner.error
        self.runner.rods_off()

    def finish(self, t_start: float, t_end: float) -> None:
        result = self.runner.finish(self.ctx.folder, self.step.name)
        self.ctx.record_result(self.step.name, result)
        link = result["flight_computer"]
        level = "warning" if result["late_ticks"] or (link and link["missed"]) else "info"
        self.ctx.event(level, f"closed loop '{self.step.name}': {result['summary']}")

    def abort(self) -> None:
        """The run is ending: the loop stops before the safe state is made (a command in flight
        finishes first, so none can follow the switch-off)."""
        self.runner.halt()
        if self._thread is not None:
            self._thread.join(timeout=ABORT_JOIN_S)
        self._detach()
        self.runner.close()


def _detumble_line(r: dict[str, Any]) -> str:
    """Through the cage against all in software, and the difference: what the hardware changed."""
    nan = float("nan")
    until = float(r.get("until_deg_s") or 0.0)
    goal = f"below {until:g} deg/s" if until > 0 else "(no detumble rate set)"
    cage, soft, diff = r.get("detumble_s"), r.get("software_detumble_s"), r.get("difference_pct")
    through = (f"{cage:.1f} s" if cage is not None
               else f"not reached ({float(r.get('final_rate_deg_s') or nan):.2f} deg/s at the end)")  # fmt: skip
    software = f"{soft:.1f} s" if soft is not None else "not reached"
    changed = f"; the hardware changed it by {diff:+.1f} %." if diff is not None else "."
    return (f"Detumble {goal}: through the cage {through}; all in software (the same scenario, a"
            f" model magnetometer with {float(r.get('noise_nt') or nan):.1f} nT of noise)"
            f" {software}{changed}")  # fmt: skip


KIND = ClosedLoop()
