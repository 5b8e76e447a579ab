"""The run's health monitor: a thread that reads back the load and coil currents and watches the
sensors and the store at about 5 Hz. A tripped supply, a stalled or frozen sensor, an output that
stopped answering, a store that cannot write or a run closed by another process while this one was
stopped (ADR 0036) is a fault (``RigSession.fail``): the main thread
raises it at its next wait and the run ends through the safe path. It watches on the process's
clock (:mod:`timebase`); in simulated time no wait of it is the computer's (no CPU-wait log)."""

from __future__ import annotations

import math
from collections.abc import Callable

import timebase
from drivers.errors import DeviceError
from rig.config import RigConfig
from rig.engine.commands import LoadBook
from rig.engine.cpu_wait import CpuWaitLog
from rig.engine.sampling import SensorSampler
from rig.engine.session import RigSession
from rig.store.run_store import RunWriter

MONITOR_PERIOD_S = 0.2
OWN_STALL_S = 0.3
"""The monitor woke this much later than its period: our own process was descheduled."""
COIL_CHECK_S = 1.0
"""How often the coil supplies' protection flags are read."""
POWER_TOLERANCE = 0.05
"""A read-back power (V_out x I_out) more than this fraction above an output's ``max_power_w``
(and :data:`POWER_FLOOR_W` more) is a fault: the read-back's own resolution and a set-point's
overshoot stay within it."""
POWER_FLOOR_W = 0.1
UNREAD_FAULT_AFTER = 2
"""Read-backs of an output that failed in a row (each after the link's own retries) before the
output counts as lost: one can be a glitch, two mean its state is unknown (a fault)."""


def closed_by_other_line(stored: str) -> str:
    """The one line of a run another process closed while this one was stopped (``stored``: the
    status and reason that process wrote, :attr:`RunWriter.closed_by_other`)."""
    return (
        f"the run was closed by another process while this one was stopped (stored: {stored});"
        " outputs switched off and nothing more recorded, its data kept as that process sealed"
        " it: start a new run"
    )


class HealthMonitor:
    """Watches one run from its own thread (:meth:`start`, :meth:`stop`)."""

    def __init__(self, rig: RigSession, writer: RunWriter, cfg: RigConfig,
                 samplers: dict[str, SensorSampler], loads: LoadBook,
                 event: Callable[[str, str], None]) -> None:  # fmt: skip
        self.rig = rig
        self.writer = writer
        self.cfg = cfg
        self.samplers = samplers
        self.loads = loads
        self.event = event
        self._unread: dict[str, int] = {}  # output -> read-backs failed in a row
        # our threads' waits for a CPU, noted every round (none to discount in simulated time)
        self._cpu_wait = None if timebase.is_simulated() else CpuWaitLog()
        self._coil_checked = -math.inf
        self._stop = timebase.Event()
        self._thread = timebase.Thread(self._monitor, name="current-monitor", daemon=True)

    def start(self) -> None:
        """Start watching."""
        self._thread.start()

    def stop(self) -> None:
        """Stop watching (waits up to 2 s for the thread)."""
        self._stop.set()
        self._thread.join(2.0)

    def _monitor(self) -> None:
        """If the watching itself fails, nothing watches the run any more: that is a fault too."""
        try:
            self._watch()
        except Exception as exc:  # a monitor that died silently would leave the run unwatched
            self.rig.fail(f"the health monitor stopped ({type(exc).__name__}: {exc}); the run is"
                          " no longer watched, so it ends here: report this")  # fmt: skip

    def _watch(self) -> None:
        last = timebase.monotonic()
        while not self._stop.wait(MONITOR_PERIOD_S):
            now = timebase.monotonic()
            # This thread woke late: the whole process was descheduled (a busy computer). The
            # samplers were too and need a moment to hand over what their sensors sent meanwhile,
            # so their freshness is judged on the next round, not now.
            own_stall = now - last > MONITOR_PERIOD_S + OWN_STALL_S
            self.read_loads()
            self.check(judge_sensors=not own_stall)
            # only the wait is judged for oversleeping: slow load read-backs (a busy bus, long
            # retries) must not count as this process being descheduled, or a frozen sensor
            # would never be judged (a stuck DUT ran on for 27 s under a CPU hog)
            last = timebase.monotonic()

    def read_loads(self) -> None:
        """Read back every load's current; a tripped load is a fault."""
        book = self.loads
        for name, load in list(book.loads.items()):
            try:
                # On a slow link a read can overlap a change of the same channel (seen: 2.5 A
                # read back 40 ms after the 0 A command, taken as the current for 0.5 s):
                # such a reading is dropped; any other holds from when it was asked.
                t_asked = timebase.monotonic()
                reading = load.read()
                started, ended = book.changing.get(name, (math.inf, math.inf))
                if started <= timebase.monotonic() and ended >= t_asked:
                    continue  # the current changed while it was read: which one is it?
                book.measured[name] = (t_asked, float(reading.i_out_a))
                self.writer.add_channel(  # known to within the exchange (ADR 0020)
                    t_asked, name, book.commanded.get(name), float(reading.i_out_a),
                    timebase.monotonic() - t_asked,
                )  # fmt: skip
                if reading.protection:
                    self.rig.fail(f"{name}: the output tripped ({reading.protection}) and is off;"
                                  " check the wiring and the load before running again")  # fmt: skip
                self._check_power(name, load, reading.v_out_v, reading.i_out_a)
                self._unread.pop(name, None)
            except (DeviceError, OSError) as exc:
                self._not_answering(name, exc)

    def _check_power(self, name: str, load: object, v_out_v: float, i_out_a: float) -> None:
        """A read-back power (W) beyond the output's ``max_power_w`` is a fault (ADR 0035)."""
        limits = getattr(load, "limits", None)
        limit_w = getattr(limits, "max_power_w", None)
        if limit_w is None:
            return
        watts = abs(float(v_out_v) * float(i_out_a))
        if watts > limit_w * (1.0 + POWER_TOLERANCE) + POWER_FLOOR_W:
            self.rig.fail(f"{name}: it delivers {watts:.1f} W ({float(v_out_v):.2f} V x"
                          f" {abs(float(i_out_a)):.3f} A read back), beyond its {limit_w:g} W"
                          " max_power_w; outputs switched off: check what it drives (a lower"
                          " resistance, a short) and its compliance_v")  # fmt: skip

    def check(self, judge_sensors: bool = True) -> None:
        """One round: the store, the sensors (unless this process was just descheduled), and
        every COIL_CHECK_S the coil supplies (``RigSession.check_coils``)."""
        w = self.writer
        if w.closed_by_other is not None:
            self.rig.fail(closed_by_other_line(w.closed_by_other))
        if w.error is not None:
            self.rig.fail(f"cannot write the run data ({w.error}): is the disk full? Free space"
                          f" under {w.folder.parent}; what was recorded before is kept")  # fmt: skip
        now = timebase.monotonic()
        if self._cpu_wait is not None:
            self._cpu_wait.note(now)
        for name, sampler in list(self.samplers.items()) if judge_sensors else []:
            # a sensor that sends nothing for its stall_after_s (declared default 1.5 s) or five
            # of its periods has stalled; its stuck_after (0: never) identical readings is frozen
            dev = self.cfg.devices[name]
            stall_s = max(float(dev.get("stall_after_s")), 5.0 / sampler.rate_hz)
            stuck_after = int(dev.get("stuck_after")) or 10**9
            problem = sampler.health(now, stall_s, stuck_after, self._cpu_wait)
            if problem is not None:
                self.rig.fail(problem)
        if self._coil_check_due(now):
            self.rig.check_coils(self._coil_read, self._not_answering)

    def _coil_read(self, t_asked: float, channel: str, amps: float) -> None:
        self._unread.pop(channel, None)  # read now: known to within the exchange (ADR 0020)
        self.writer.add_channel(t_asked, channel, None, amps, timebase.monotonic() - t_asked)

    def _not_answering(self, name: str, exc: Exception) -> None:
        """An output that did not answer a read-back (its link already retried): a warning the
        first time; UNREAD_FAULT_AFTER times in a row, a fault (its state is no longer known)."""
        self._unread[name] = self._unread.get(name, 0) + 1
        if self._unread[name] >= UNREAD_FAULT_AFTER:
            self.rig.fail(f"{exc}; {name} stopped answering, so its output is not under control")
        else:
            self.event("warning", f"reading {name}: {exc}")

    def _coil_check_due(self, now: float) -> bool:
        if now - self._coil_checked < COIL_CHECK_S:
            return False
        self._coil_checked = now
        return True
