"""The closed loop as it runs (:mod:`rig.steps.closed_loop`): the scenario from the step's
parameters, the ticks on the run's clock, the DUT's readings in, the cage's field out, the
per-tick record and, at the end, the all-software run it is compared with."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

import timebase
from rig.calibration.record import latest_calibration
from rig.errors import RigError
from rig.hil.dynamics import Spacecraft
from rig.hil.external import ExternalFlightComputer
from rig.hil.flight_software import BDot, FlightSoftware, default_gain
from rig.hil.loop import Loop, LoopPlan, OrbitField, Tick, percentile_ms, software_only
from rig.hil.torque_rods import RodLog, TorqueRods, stray_bias_ut
from rig.steps.base import Array, RunContext
from rig.steps.closed_loop_ticks import write_ticks
from rig.steps.null_field import latest_noise_floor
from rig.steps.vocabulary import FieldCommand, FieldPayload, LoadCommand, Step

DEFAULT_NOISE_NT = 20.0
"""The all-software run's magnetometer noise (nT) when neither ``noise_nt`` nor a null field of
the run gives the DUT's."""
LATE_LOGGED = 3
"""Late ticks logged one by one before only the count goes on."""
TICK_AFTER_READING = 0.25
"""The first tick comes this fraction of a period after a DUT reading arrives (room for the
arrival's jitter); LOCK_WAIT_PERIODS: how long the loop waits for that reading (periods)."""
LOCK_WAIT_PERIODS = 3.0
FIELD_MODEL = "IGRF (ppigrf) along the TLE's orbit (sgp4), turned into the body by the attitude"
DYNAMICS = "Basilisk Spacecraft hub (rigid body) with an MtbEffector (three torque rods)"


def mrp_to_dcm(mrp: Array) -> Array:
    """[BN] of modified Rodrigues parameters (rows: body axes in the inertial frame)."""
    s = np.asarray(mrp, float)
    s2 = float(s @ s)
    k = np.array([[0.0, -s[2], s[1]], [s[2], 0.0, -s[0]], [-s[1], s[0], 0.0]])
    return np.asarray(np.eye(3) + (8.0 * k @ k - 4.0 * (1.0 - s2) * k) / (1.0 + s2) ** 2)


@dataclass(frozen=True)
class Scenario:
    """The step's spacecraft, orbit and loop, from its parameters."""

    params: dict[str, Any]

    @cached_property
    def orbit(self) -> OrbitField:
        """The orbit's inertial field on a 1 s grid of orbit time over the step (uT)."""
        from rig.steps.orbit import orbit_track, parse_start

        p = self.params
        span = float(p["duration_s"]) * float(p["time_scale"]) + 2.0
        t = np.arange(0.0, span + 1.0, 1.0)
        track = orbit_track(p["tle"][0], p["tle"][1], parse_start(p["start"]), t, "inertial")
        return OrbitField(t, track.field_body_ut, float(p["time_scale"]))

    @property
    def craft(self) -> Spacecraft:
        p = self.params
        ixx, iyy, izz = (float(v) for v in p["inertia_kg_m2"])
        rate = tuple(float(v) for v in p["rate_deg_s"])
        return Spacecraft(((ixx, 0.0, 0.0), (0.0, iyy, 0.0), (0.0, 0.0, izz)),
                          float(p["max_dipole_am2"]), (rate[0], rate[1], rate[2]))  # fmt: skip

    @property
    def plan(self) -> LoopPlan:
        p = self.params
        return LoopPlan(float(p["rate_hz"]), float(p["control_hz"]), float(p["duration_s"]),
                        float(p["until_deg_s"]))  # fmt: skip

    def software(self) -> FlightSoftware:
        """The flight software for one run: the external flight computer when the step names
        one (the all-software run then uses it too: software in the loop), else a fresh B-dot."""
        address = str(self.params["flight_computer"])
        if address:
            return ExternalFlightComputer(address, float(self.params["reply_timeout_s"]))
        dipole = float(self.params["max_dipole_am2"])
        return BDot(float(self.params["gain"]) or default_gain(dipole), dipole)

    @cached_property
    def rods(self) -> TorqueRods | None:
        return TorqueRods.of(self.params)

    @property
    def software_name(self) -> str:
        address = str(self.params["flight_computer"])
        return f"external flight computer at {address}" if address else "B-dot in process"

    @property
    def scale(self) -> float:
        return float(self.params["field_scale"])

    def initial_field_ut(self) -> Array:
        """The field the cage makes first (uT, cage frame, scaled)."""
        c_bn = mrp_to_dcm(np.array(self.craft.mrp))
        return np.asarray(c_bn @ self.orbit.at(0.0)) * self.scale

    def peak_field_ut(self) -> float:
        """The largest field the loop may ask of the cage, in any direction (uT, scaled)."""
        return self.orbit.peak_ut * self.scale


def scenario_of(params: dict[str, Any]) -> Scenario:
    return Scenario(params)


class LoopRunner:
    """The loop's thread (:meth:`run`), fed by the DUT's sampler (:meth:`on_sample`)."""

    def __init__(self, ctx: RunContext, step: Step, dut: str) -> None:
        self.ctx, self.step = ctx, step
        self.scenario = scenario_of(step.params)
        self.rods = self.scenario.rods
        self.rod_log = RodLog()
        self.rod_a: list[Array] = []  # per tick: the rods' currents over it (A; NaN: no rod)
        self.correction = self._correction(ctx, step, self.rods)
        self.loop = Loop(self.scenario.craft, self.scenario.plan, self.scenario.orbit,
                         self.scenario.software())  # fmt: skip
        self.detumbled = timebase.Event()
        self._halt = timebase.Event()
        self._lock = timebase.Lock()
        self._pending: list[tuple[float, Array]] = []
        self._arrived = timebase.Event()  # set by every DUT reading
        self.ticks: list[Tick] = []
        self.latency_s: list[float] = []
        self.late = 0
        self.samples = 0
        self.error: BaseException | None = None

    @staticmethod
    def _correction(ctx: RunContext, step: Step,
                    rods: TorqueRods | None) -> tuple[Array, Array, dict[str, Array]] | None:  # fmt: skip
        """(matrix, offset uT, current-to-bias coefficients uT/A per load channel) of the run's
        latest calibration for ``readings: calibrated``."""
        if step.params["readings"] != "calibrated":
            return None
        found = latest_calibration(ctx.results)
        if found is None:
            raise RigError(
                f"{step.where}: closed_loop with readings: calibrated needs a calibration earlier"
                " in the run (a calibrate or live_calibrate step), or readings: raw"
            )
        name, cal = found
        k = {ch: np.asarray(v, float) for ch, v in cal.k_ut_per_unit.items()}
        unfitted = [ch for ch in (rods.used if rods is not None else ()) if ch not in k]
        if unfitted:
            raise RigError(
                f"{step.where}: closed_loop with readings: calibrated and a torque rod on"
                f" {unfitted[0]} needs a calibration that fitted {unfitted[0]}'s current-to-bias"
                f" coefficients ('{name}' did not: add it to the calibrate step's telemetry)"
            )
        corr = cal.correction
        return np.array(corr["matrix"], float), np.array(corr["offset_ut"], float), k

    def on_sample(self, t: float, xyz: tuple[float, float, float]) -> None:
        """A DUT reading (its sampler's thread): kept for the tick after it."""
        with self._lock:
            self._pending.append((t, np.asarray(xyz, float)))
            self.samples += 1
        self._arrived.set()

    def _phase_locked_start(self, period_s: float) -> float:
        """When the first tick is due (monotonic s): :data:`TICK_AFTER_READING` of a period after
        the next DUT reading arrives, so that a DUT sampling at the tick rate has each reading
        used by the tick just after it, not up to a period later (50 Hz: 5 ms, not 0-20 ms)."""
        self._arrived.clear()
        self._arrived.wait(LOCK_WAIT_PERIODS * period_s)
        return timebase.monotonic() + TICK_AFTER_READING * period_s

    def status(self) -> str:
        rate = float(np.linalg.norm(self.ticks[-1].rate_deg_s)) if self.ticks else math.nan
        return f"closed loop: t {self.loop.t_s:.1f} s, body rate {rate:.2f} deg/s"

    def halt(self) -> None:
        self._halt.set()

    def close(self) -> None:
        """The run ended before the step's result: let go of an external flight computer."""
        _close_link(self.loop.software)

    def _body_reading(self, xyz: Array, t_s: float) -> Array:
        """The DUT's reading dated ``t_s`` (monotonic s) as the flight software gets it (uT):
        corrected when asked (the loads' bias from their currents then, the rods' as the loop
        commanded them), and divided by the field scale (the flight software sees the orbit's
        field)."""
        if self.correction is not None:
            matrix, offset, k = self.correction
            currents = dict(self.ctx.commanded_loads) | self.rod_log.at(t_s)
            xyz = matrix @ (xyz - offset - stray_bias_ut(k, currents))
        return np.asarray(xyz / self.scenario.scale)

    def _command_rods(self, dipole_am2: Array) -> None:
        """The rods' currents for the dipole the flight software holds from now."""
        if self.rods is None:
            return
        currents = self.rods.currents_a(dipole_am2)
        if currents == (self.rod_log.currents_a[-1] if self.rod_log.currents_a else None):
            return
        for ch, amps in currents.items():
            self.ctx.command(self.step.index, LoadCommand(0.0, {"channel": ch, "current_a": amps}),
                             timebase.monotonic())  # fmt: skip
        self.rod_log.add(timebase.monotonic(), currents)

    def rods_off(self) -> None:
        """The step ended: the rods' loads to 0 A (a run that ends otherwise: the safe state)."""
        if self.rods is None:
            return
        for ch in self.rods.used:
            self.ctx.command(self.step.index, LoadCommand(0.0, {"channel": ch, "current_a": 0.0}),
                             timebase.monotonic())  # fmt: skip

    def _rod_row(self) -> Array:
        """The rods' currents now (A) in body-axis order, NaN for an axis without one."""
        if self.rods is None or not self.rod_log.currents_a:
            return np.full(3, math.nan)
        now = self.rod_log.currents_a[-1]
        return np.array([now[ch] if ch is not None else math.nan for ch in self.rods.channels])

    def run(self) -> None:
        """Tick until detumbled, out of time or halted; an exception is kept for wind_down."""
        try:
            self._ticks()
        except BaseException as exc:  # the run's thread re-raises it, through the safe path
            self.error = exc
        finally:
            self.detumbled.set()  # the step's timeline ends now either way

    def _ticks(self) -> None:
        loop, period = self.loop, 1.0 / self.scenario.plan.rate_hz
        t0 = self._phase_locked_start(period)
        with self._lock:  # readings of the ramp to the starting field are not the loop's
            self._pending = [(t, xyz) for t, xyz in self._pending if t >= t0]
        if self.rods is not None:  # the step's first commands set them at rest
            self.rod_log.add(t0, self.rods.currents_a(np.zeros(3)))
        held = loop.field_now()  # made by the step's starting command
        newest: float | None = None  # the newest reading handed to the loop (monotonic s)
        while not loop.done and not self._halt.is_set():
            due = t0 + loop.k * period
            if self._halt.wait(max(0.0, due - timebase.monotonic())):
                break
            with self._lock:
                pending, self._pending = self._pending, []
            for t, xyz in pending:
                loop.reading(self._body_reading(xyz, t), t - t0)
                newest = t if newest is None else max(newest, t)
            tick = loop.advance(held)
            self.ticks.append(tick)
            self.rod_a.append(self._rod_row())
            held = loop.field_now()
            if self._halt.is_set():  # the run is ending: no command after the halt
                self.latency_s.append(math.nan)  # (one per tick in the record)
                break
            tracked: FieldPayload = {"field_ut": [float(v) for v in held * self.scenario.scale],
                                     "track": True}  # fmt: skip
            self.ctx.command(self.step.index, FieldCommand(0.0, tracked), timebase.monotonic())
            sent = timebase.monotonic()
            self._command_rods(loop.dipole)  # after the field: its latency is the field's
            # from the newest reading behind a new dipole to the command that carries it
            self.latency_s.append(sent - newest if tick.reading_ut is not None and newest
                                  is not None else math.nan)  # fmt: skip
            if sent > due + period:
                self._late(loop.k - 1, sent - due)
        if loop.detumbled_at_s is not None:
            self.detumbled.set()

    def _late(self, k: int, late_s: float) -> None:
        """Count a tick whose command went out more than a period after it was due; the first
        few are logged one by one, the count always goes to the result."""
        self.late += 1
        if self.late <= LATE_LOGGED:
            more = " (later ones are counted, not logged)" if self.late == LATE_LOGGED else ""
            self.ctx.event("warning", f"closed loop: tick {k} sent {1000.0 * late_s:.0f} ms after"
                                      f" it was due{more}")  # fmt: skip

    def finish(self, folder: Path, name: str) -> dict[str, Any]:
        """The all-software run of the same scenario, the per-tick records and the result."""
        noise_nt = self._noise_nt()
        scenario = self.scenario
        software = scenario.software()
        try:
            ticks_sw, detumble_sw = software_only(scenario.craft, scenario.plan, scenario.orbit,
                                                  software, noise_nt / 1000.0, self._dut_rate_hz(),
                                                  int(scenario.params["seed"]))  # fmt: skip
        finally:
            _close_link(software)
        slug = re.sub(r"[^A-Za-z0-9]+", "-", name).strip("-").lower() or "loop"
        files = (f"closed-loop-{slug}.csv", f"closed-loop-{slug}-software.csv")
        latency = self.latency_s
        write_ticks(folder / files[0], self.ticks, latency, self.rod_a)
        write_ticks(folder / files[1], ticks_sw, [math.nan] * len(ticks_sw),
                     [np.full(3, math.nan)] * len(ticks_sw))  # fmt: skip
        return _result(self, detumble_sw, noise_nt, latency, files)

    def _noise_nt(self) -> float:
        given = float(self.step.params["noise_nt"])
        if given > 0:
            return given
        floor = latest_noise_floor(self.ctx.results)
        role = self.step.params["magnetometer"]
        found = floor.noise_nt.get(role) if floor is not None else None
        return float(found) if found is not None else DEFAULT_NOISE_NT

    def _dut_rate_hz(self) -> float:
        """The DUT's readings per second over the loop (the all-software run samples so)."""
        span = self.loop.t_s
        return self.samples / span if span > 0 and self.samples else 20.0


def _close_link(software: Any) -> dict[str, Any] | None:
    """Close an external flight computer's link; its answers, misses, first problem and round
    trip (ms). None for the in-process flight software."""
    if not isinstance(software, ExternalFlightComputer):
        return None
    software.close()
    return {"answered": software.answered, "missed": software.missed, "problem": software.problem,
            "round_trip_ms_p99": percentile_ms(software.round_trips_s, 99)}  # fmt: skip


def _result(run: LoopRunner, detumble_sw: float | None, noise_nt: float, latency: list[float],
            files: tuple[str, str]) -> dict[str, Any]:  # fmt: skip
    detumble = run.loop.detumbled_at_s
    final = float(np.linalg.norm(run.ticks[-1].rate_deg_s)) if run.ticks else math.nan
    diff = (100.0 * (detumble - detumble_sw) / detumble_sw
            if detumble is not None and detumble_sw else None)  # fmt: skip
    until = float(run.step.params["until_deg_s"])
    said = (f"detumbled below {until:g} deg/s in {detumble:.1f} s (all software: "
            + (f"{detumble_sw:.1f} s, {diff:+.1f} %)" if detumble_sw and diff is not None
               else "not within the step)")
            if detumble is not None else f"body rate {final:.2f} deg/s at the end")  # fmt: skip
    late = f"; {run.late} of {len(run.ticks)} ticks late (more than a period)" if run.late else ""
    link = _close_link(run.loop.software)
    if link is not None and link["missed"]:
        late += (f"; the flight computer did not answer {link['missed']} of"
                 f" {link['missed'] + link['answered']} periods (first: {link['problem']})")  # fmt: skip
    p99 = percentile_ms(latency, 99)
    return {
        "detumble_s": detumble, "software_detumble_s": detumble_sw, "difference_pct": diff,
        "final_rate_deg_s": final, "ticks": len(run.ticks), "late_ticks": run.late,
        "latency_ms": {"p50": percentile_ms(latency, 50), "p99": p99,
                       "max": percentile_ms(latency, 100)},
        "until_deg_s": until, "flight_software": run.scenario.software_name,
        "flight_computer": link,
        "readings": run.step.params["readings"], "field_model": FIELD_MODEL, "dynamics": DYNAMICS,
        "noise_nt": noise_nt, "peak_field_ut": run.scenario.peak_field_ut(),
        "history_file": files[0], "software_history_file": files[1],
        "torque_rods": _rods_result(run),
        "summary": f"{said}{late}; latency p99 {p99:.0f} ms",
    }  # fmt: skip


def _rods_result(run: LoopRunner) -> dict[str, Any] | None:
    """The rods as they ran: channels, scale and bias, and how often their currents changed."""
    rods = run.rods
    if rods is None:
        return None
    return {"channels": [c or "none" for c in rods.channels], "a_per_am2": rods.a_per_am2,
            "bias_a": rods.bias_a, "changes": max(len(run.rod_log.times_s) - 1, 0)}  # fmt: skip
