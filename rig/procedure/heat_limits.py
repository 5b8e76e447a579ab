"""What a procedure asks of its load channels beyond their own limits, known before any device is
opened (ADR 0035): printed by ``rig check`` as ``LIMIT:`` lines, refused by ``rig run`` before the
lock or any output.

For every load set-point of the plan (its steps' load profiles, each channel back to 0 A at a
step's end):

* its current against the output's ``max_current_a`` and the range its kind and configuration
  state without opening it (a register map's; the largest of a Riden's family), and its sign for
  an output that drives current one way only;
* its worst-case power ``|I| x V`` against ``max_power_w``, ``V`` the voltage the output may
  reach: ``compliance_v`` within ``max_voltage_v`` and the range, or for an electronic load (no
  voltage set-point) ``max_voltage_v`` or its range, as :class:`rig.output_limits.LimitedOutput`
  judges it at run time;
* for an output that ``heats`` a thermometer with ``max_temperature_c``: the temperature the plan
  takes the DUT to, ``ambient_c`` of the thermometer (25 C unless given) plus, per heater,
  ``kelvin_per_w`` times its power relaxed first-order with ``thermal_tau_s`` (at once without
  it) over the plan's own profile; the power is ``min(|I|, V/R)^2 R`` with ``resistance_ohm``,
  else the worst case ``|I| x V``. Prompts count as taking no time, so no cooling is assumed.

One sentence per problem (the worst set-point of each step and channel; per thermometer, the
first step it is predicted beyond its limit), each naming the step, the output, the value, the
limit and the fix.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

from drivers.registry import KINDS, output_range
from rig.config import DeviceConfig, RigConfig
from rig.procedure.plan import compile_plan, rig_timing
from rig.steps import KINDS as STEP_KINDS
from rig.steps.vocabulary import LoadCommand, Procedure, Step

TOLERANCE = 1e-9
"""Values this close above a limit count as at it (floating-point rounding)."""


@dataclass(frozen=True)
class LoadOutput:
    """One load channel's limits and heating, from its configuration alone."""

    name: str
    max_current_a: float | None
    current_from: str
    one_way: str
    """Where it is known to drive current one way only (words); "" if signed or not known."""
    reach_v: float | None
    """The most voltage (V) it may put across what it drives; None: not known."""
    reach_from: str
    max_power_w: float | None
    heats: str | None
    kelvin_per_w: float | None
    tau_s: float | None
    resistance_ohm: float | None

    @classmethod
    def of(cls, dev: DeviceConfig) -> LoadOutput:
        """The limits of output ``dev`` (units as its keys)."""
        rng = output_range(dev.kind, dev.params)
        limits = [(float(dev.get("max_current_a")), f"max_current_a of [devices.{dev.name}]")
                  ] if dev.get("max_current_a") is not None else []  # fmt: skip
        if rng is not None:
            limits.append((rng.max_current_a, rng.source))
        amps, amps_from = min(limits, key=lambda x: x[0]) if limits else (None, "")
        volts = [(float(dev.get("max_voltage_v")), f"max_voltage_v of [devices.{dev.name}]")
                 ] if dev.get("max_voltage_v") is not None else []  # fmt: skip
        if rng is not None:
            volts.append((rng.max_voltage_v, rng.source))
        if rng is None or rng.sets_voltage:
            volts.append((float(dev.get("compliance_v", 12.0)), "its compliance_v"))
        reach, reach_from = min(volts, key=lambda x: x[0]) if volts else (None, "")
        one_way = f"a {dev.kind}" if rng is not None and not rng.bipolar else ""
        return cls(dev.name, amps, amps_from, one_way, reach, reach_from,
                   _number(dev, "max_power_w"), dev.get("heats"), _number(dev, "kelvin_per_w"),
                   _number(dev, "thermal_tau_s"), _number(dev, "resistance_ohm"))  # fmt: skip

    def heating_w(self, amps: float) -> float:
        """The power (W) it puts into its heater at ``amps`` (A): ``min(|I|, V/R)^2 R`` with a
        resistance, else the worst case ``|I| x V`` (V unknown: infinite)."""
        volts = math.inf if self.reach_v is None else self.reach_v
        if self.resistance_ohm is not None:
            return min(abs(amps), volts / self.resistance_ohm) ** 2 * self.resistance_ohm
        return abs(amps) * volts if amps else 0.0


def _number(dev: DeviceConfig, key: str) -> float | None:
    value = dev.get(key)
    return None if value is None else float(value)


@dataclass(frozen=True)
class SetPoint:
    """A load set-point of the plan: its time from the start (s), step, channel and current (A)."""

    t_s: float
    step: Step
    channel: str
    current_a: float


def plan_setpoints(proc: Procedure, cfg: RigConfig) -> Iterator[SetPoint]:
    """Every load set-point of the plan in time order (a step's own duration, prompts as 0 s)."""
    t0 = 0.0
    for plan in compile_plan(proc, rig_timing(cfg)):
        for c in plan.commands:
            if isinstance(c, LoadCommand):
                yield SetPoint(t0 + c.t_s, plan.step, c.payload["channel"], c.payload["current_a"])
        # what a step may set only as it runs (a closed loop's rods): its largest, from its start
        for channel, amps in STEP_KINDS[plan.step.kind].load_envelope_a(plan.step).items():
            yield SetPoint(t0, plan.step, channel, amps)
        t0 += plan.duration_s


def _step(s: Step) -> str:
    return f"{s.where}: step {s.index + 1} ({s.name})"


def _load_outputs(proc: Procedure, cfg: RigConfig) -> dict[str, LoadOutput]:
    """The procedure's load channels that are load-capable devices of ``cfg`` (the others are
    refused elsewhere: an unknown name, a cage device)."""
    return {name: LoadOutput.of(cfg.devices[name]) for name in proc.loads
            if name in cfg.devices and cfg.devices[name].kind in KINDS
            and "load" in KINDS[cfg.devices[name].kind].roles}  # fmt: skip


def heater_refusals(proc: Procedure, cfg: RigConfig | None) -> list[str]:
    """One sentence per load set-point beyond its output's current or power limit and per
    thermometer the plan is predicted to take beyond its ``max_temperature_c``; empty without a
    rig configuration or loads."""
    if cfg is None or not proc.loads:
        return []
    outputs = _load_outputs(proc, cfg)
    if not outputs:
        return []
    problems = _declarations(outputs, cfg)
    setpoints = [p for p in plan_setpoints(proc, cfg) if p.channel in outputs]
    worst: dict[tuple[int, str], SetPoint] = {}
    for p in setpoints:
        key = (p.step.index, p.channel)
        if key not in worst or abs(p.current_a) > abs(worst[key].current_a):
            worst[key] = p
        if p.current_a < 0 and outputs[p.channel].one_way:
            worst[(p.step.index, p.channel + "\0sign")] = p
    for key, p in worst.items():
        out = outputs[p.channel]
        if key[1].endswith("\0sign"):
            problems.append(f"{_step(p.step)}: load {out.name} at {p.current_a:g} A, but"
                            f" {out.name} drives current one way only ({out.one_way}):"
                            " write a set-point of 0 A or more")  # fmt: skip
            continue
        problems += _current_and_power(p, out)
    problems += _temperatures(setpoints, outputs, cfg)
    return problems


def _declarations(outputs: dict[str, LoadOutput], cfg: RigConfig) -> list[str]:
    """A ``heats`` that names no thermometer, or one without ``kelvin_per_w`` (nothing can be
    predicted)."""
    thermometers = [n for n, d in cfg.devices.items()
                    if d.kind in KINDS and "thermometer" in KINDS[d.kind].roles]  # fmt: skip
    problems = []
    for out in outputs.values():
        if out.heats is None:
            continue
        if out.heats not in thermometers:
            problems.append(f"{cfg.path}: [devices.{out.name}] heats = \"{out.heats}\" names no"
                            " thermometer of the rig: name one of"
                            f" {', '.join(thermometers) or '(none declared)'}")  # fmt: skip
        elif out.kelvin_per_w is None:
            problems.append(f"{cfg.path}: [devices.{out.name}] heats \"{out.heats}\" but has no"
                            " kelvin_per_w, so its warming cannot be predicted: write the rise"
                            " per watt, e.g. kelvin_per_w = 2.0")  # fmt: skip
    return problems


def _current_and_power(p: SetPoint, out: LoadOutput) -> list[str]:
    """The set-point ``p`` against the current and the power limit of ``out``."""
    amps = abs(p.current_a)
    if out.max_current_a is not None and not amps <= out.max_current_a + TOLERANCE:
        return [f"{_step(p.step)}: load {out.name} at {p.current_a:g} A is beyond its"
                f" {out.max_current_a:g} A limit ({out.current_from}): lower the set-point to at"
                f" most {out.max_current_a:g} A"]  # fmt: skip
    if out.max_power_w is None or not amps:
        return []
    if out.reach_v is None:
        return [f"{_step(p.step)}: load {out.name} has max_power_w = {out.max_power_w:g} W but"
                " no known voltage, so its worst-case power cannot be judged: write its"
                " max_voltage_v"]  # fmt: skip
    watts = amps * out.reach_v
    if watts <= out.max_power_w * (1.0 + TOLERANCE) + TOLERANCE:
        return []
    return [f"{_step(p.step)}: load {out.name} at {p.current_a:g} A may deliver {watts:g} W"
            f" (worst case {amps:g} A x {out.reach_v:g} V, {out.reach_from}), beyond its"
            f" max_power_w of {out.max_power_w:g} W: ask at most"
            f" {out.max_power_w / out.reach_v:.3g} A, or lower the voltage it may reach"
            " (compliance_v, max_voltage_v)"]  # fmt: skip


@dataclass
class _Warming:
    """One thermometer's predicted rise above ambient per heater (K), walked through the plan."""

    heaters: dict[str, LoadOutput]
    rise_k: dict[str, float] = field(default_factory=dict)
    target_k: dict[str, float] = field(default_factory=dict)
    t_s: float = 0.0

    def advance(self, t_s: float) -> float:
        """Relax every heater's rise to time ``t_s`` (s); returns the most the summed rise (K)
        can have reached on the way (each rise is monotonic between set-points)."""
        dt = max(0.0, t_s - self.t_s)
        peak = 0.0
        for name, out in self.heaters.items():
            before, target = self.rise_k.get(name, 0.0), self.target_k.get(name, 0.0)
            after = target + (before - target) * math.exp(-dt / out.tau_s) if out.tau_s else target
            self.rise_k[name] = after
            peak += max(before, after)
        self.t_s = max(self.t_s, t_s)
        return peak

    def set(self, out: LoadOutput, amps: float) -> float:
        """Heater ``out`` at ``amps`` (A) from now; returns the summed rise (K) right after (a
        heater without a time constant reaches its steady state at once)."""
        assert out.kelvin_per_w is not None
        self.target_k[out.name] = out.kelvin_per_w * out.heating_w(amps)
        if not out.tau_s:
            self.rise_k[out.name] = self.target_k[out.name]
        return sum(self.rise_k.values())


def _temperatures(setpoints: list[SetPoint], outputs: dict[str, LoadOutput],
                  cfg: RigConfig) -> list[str]:  # fmt: skip
    """Per thermometer with ``max_temperature_c`` that the procedure's loads heat, the plan's
    predicted peak temperature against it."""
    problems = []
    for name, dev in cfg.devices.items():
        limit = dev.get("max_temperature_c")
        heaters = {n: o for n, o in outputs.items()
                   if o.heats == name and o.kelvin_per_w is not None}  # fmt: skip
        if limit is None or not heaters:
            continue
        ambient = float(dev.get("ambient_c", 25.0))
        warming = _Warming(heaters)
        first: SetPoint | None = None
        peak_k, peak_at = 0.0, None
        driving: SetPoint | None = None  # the latest heater set-point: what drives the rise
        for p in setpoints:
            if p.channel not in heaters:
                continue
            for rise, by in ((warming.advance(p.t_s), driving),
                             (warming.set(heaters[p.channel], p.current_a), p)):  # fmt: skip
                if by is None:
                    continue
                if rise > peak_k:
                    peak_k, peak_at = rise, by
                if first is None and ambient + rise > float(limit) + TOLERANCE:
                    first = by
            driving = p
        if first is not None and peak_at is not None:
            problems.append(_too_hot(name, float(limit), ambient, peak_k, first, peak_at,
                                     heaters))  # fmt: skip
    return problems


def _too_hot(name: str, limit: float, ambient: float, peak_k: float, first: SetPoint,
             peak_at: SetPoint, heaters: dict[str, LoadOutput]) -> str:  # fmt: skip
    """The sentence for thermometer ``name`` predicted beyond ``limit`` (C)."""
    out = heaters[first.channel]
    assert out.kelvin_per_w is not None
    allowed_w = max(0.0, limit - ambient) / out.kelvin_per_w
    if out.resistance_ohm is not None:
        most_a = math.sqrt(allowed_w / out.resistance_ohm)
        how = f"{out.resistance_ohm:g} ohm"
    else:
        most_a = allowed_w / out.reach_v if out.reach_v else 0.0
        how = f"worst case x {out.reach_v:g} V"
    tau = f", tau {out.tau_s:g} s" if out.tau_s else ", steady state at once"
    at = "" if peak_at.step is first.step else f" by step {peak_at.step.index + 1}"
    return (
        f"{_step(first.step)}: load {out.name} at {first.current_a:g} A is predicted to"
        f" warm {name} beyond its max_temperature_c of {limit:g} C, to"
        f" {ambient + peak_k:.1f} C{at} ({ambient:g} C ambient_c of {name} +"
        f" {out.kelvin_per_w:g} K/W{tau}, power {how}): hold {out.name} at most"
        f" {most_a:.3g} A ({allowed_w:.3g} W at steady state), or shorten the heating"
    )
