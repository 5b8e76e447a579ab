"""Record a thermometer through a run: one reading a second, as a channel of the run store.

The DUT's temperature is what its temperature coefficients are fitted against
(``rig calibrate RUN --temperature NAME``). A thermometer is not an output and not a sensor the
acceptance depends on, so one that stops answering never ends a run: the first failure of a
streak is a warning, the next good reading an event saying it is back, and the gap stays visible
in the data. Its own thread, so a module that times out never delays the load read-backs or the
health checks.

A thermometer with ``max_temperature_c`` is also the DUT's temperature interlock (ADR 0035): it is
read every :data:`INTERLOCK_PERIOD_S`, a reading beyond the limit is a fault (``RigSession.fail``:
the run goes to its safe state), and so is one that has not answered for :data:`STALE_S` while an
output that ``heats`` it has a current set-point.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import timebase
from drivers.errors import DeviceError
from drivers.protocols import Thermometer

PERIOD_S = 1.0
"""Between readings (s): a DUT and its mount change temperature over minutes; RTD modules
convert a few times a second."""

INTERLOCK_PERIOD_S = 0.25
"""Between readings of an interlock thermometer (s): a reading beyond its limit reaches the safe
path within this, the exchange and a fault-aware wait (0.05 s), well within 1 s."""
STALE_S = 2.0
"""An interlock thermometer without a reading for this long (s) while a heater of its is driven is
a fault: a read that timed out once with its retries (0.5 s each) is not yet one; at the 2 K/W and
20 W of the simulated heater the DUT warms by at most 0.7 K meanwhile."""
WATCH_S = 0.1
"""The interlock's watchdog looks at the age of the latest reading when it would pass
:data:`STALE_S`, and at least this long after its last look (s)."""


@dataclass(frozen=True)
class Interlock:
    """What makes a thermometer the DUT's temperature interlock: its limit (C, its
    ``max_temperature_c``), the fault to raise (``RigSession.fail``) and the names of the run's
    outputs that warm it and have a current set-point now (``heating``)."""

    max_c: float
    fail: Callable[[str], None]
    heating: Callable[[], list[str]]


ChannelSink = Callable[[float, str, float | None, float | None, float | None], None]
"""(time s, channel, set-point, measured, time uncertainty s):
:meth:`rig.store.RunWriter.add_channel`."""


class TemperatureLog:
    """Read ``thermometer`` every ``period_s`` into ``sink`` as channel ``name`` (degrees C,
    measured column) until :meth:`stop`; ``on_event(level, message)`` hears of gaps."""

    def __init__(self, name: str, thermometer: Thermometer, sink: ChannelSink,
                 on_event: Callable[[str, str], None], period_s: float | None = None,
                 interlock: Interlock | None = None) -> None:  # fmt: skip
        self.name = name
        self.thermometer = thermometer
        self.sink = sink
        self.on_event = on_event
        self.interlock = interlock
        if period_s is None:
            period_s = PERIOD_S if interlock is None else INTERLOCK_PERIOD_S
        self.period_s = period_s
        self.readings = 0
        self.failures = 0
        self.last_reading_s = timebase.monotonic()  # when the latest good reading was asked
        self._stop = timebase.Event()
        self._thread = timebase.Thread(self._run, name=f"thermometer-{name}", daemon=True)
        self._watchdog = timebase.Thread(self._watch, name=f"interlock-{name}",
                                          daemon=True)  # fmt: skip

    def start(self) -> None:
        """Start reading (the first reading at once), and an interlock's watchdog."""
        self.last_reading_s = timebase.monotonic()
        self._thread.start()
        if self.interlock is not None:
            self._watchdog.start()

    def _judge(self, value: float) -> None:
        """A reading (C) beyond the interlock's limit (or not a number) is a fault."""
        lock = self.interlock
        if lock is None or value <= lock.max_c:
            return
        shown = f"{value:.1f} C" if math.isfinite(value) else f"{value} (not a temperature)"
        lock.fail(f"{self.name} reads {shown}, beyond its max_temperature_c of {lock.max_c:g} C;"
                  " outputs switched off: let the DUT cool, then lower the heater's current (rig"
                  " check predicts the temperature from kelvin_per_w) or, if the DUT allows it,"
                  " raise max_temperature_c")  # fmt: skip

    def _watch(self) -> None:
        """An interlock's watchdog: no reading for STALE_S while a heater of it is driven is a
        fault, even while a read hangs in its timeout."""
        lock = self.interlock
        assert lock is not None
        # asleep until the latest reading would be stale (a fresher one moves that on); once
        # stale with nothing heating, looked at every WATCH_S until something heats
        while not self._stop.wait(
            max(WATCH_S, self.last_reading_s + STALE_S - timebase.monotonic())
        ):
            age_s = timebase.monotonic() - self.last_reading_s
            if age_s > STALE_S and (heaters := lock.heating()):
                lock.fail(f"{self.name} has given no temperature for {age_s:.1f} s while"
                          f" {', '.join(heaters)} heat{'s' if len(heaters) == 1 else ''} the DUT;"
                          " outputs switched off, as the DUT's temperature is not known: check"
                          f" {self.name}'s link and wiring, then run again")  # fmt: skip
                return

    def _run(self) -> None:
        failing = False
        while True:
            t_asked = timebase.monotonic()  # the reading is from after this moment
            try:
                value = self.thermometer.read_temperature_c()
            except (DeviceError, OSError) as exc:
                self.failures += 1
                if not failing:
                    self.on_event("warning", f"{exc}; the DUT temperature is not recorded until"
                                  f" {self.name} answers again")  # fmt: skip
                failing = True
            else:
                # taken after it was asked, known to within the exchange (ADR 0020)
                self.sink(t_asked, self.name, None, value, timebase.monotonic() - t_asked)
                self._judge(value)
                self.last_reading_s = t_asked
                self.readings += 1
                if failing:
                    self.on_event("info", f"{self.name} answers again ({value:.1f} C)")
                failing = False
            if self._stop.wait(max(0.0, self.period_s - (timebase.monotonic() - t_asked))):
                return

    def stop(self) -> None:
        """Stop reading and wait for the thread (at most one reading's timeout)."""
        self._stop.set()
        for thread in (self._thread, self._watchdog):
            if thread.is_alive():
                thread.join(timeout=5.0)
