"""Record a thermometer through a run: one reading a second, as a channel of the run store.

The DUT's temperature is what its temperature coefficients are fitted against
(``rig calibrate RUN --temperature NAME``). A thermometer is not an output and not a sensor the
acceptance depends on, so one that stops answering never ends a run: the first failure of a
streak is a warning, the next good reading an event saying it is back, and the gap stays visible
in the data. Its own thread, so a module that times out never delays the load read-backs or the
health checks.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from drivers.errors import DeviceError
from drivers.protocols import Thermometer

PERIOD_S = 1.0
"""Between readings (s): a DUT and its mount change temperature over minutes; RTD modules
convert a few times a second."""

ChannelSink = Callable[[float, str, float | None, float | None, float | None], None]
"""(time s, channel, set-point, measured, time uncertainty s):
:meth:`rig.store.RunWriter.add_channel`."""


class TemperatureLog:
    """Read ``thermometer`` every ``period_s`` into ``sink`` as channel ``name`` (degrees C,
    measured column) until :meth:`stop`; ``on_event(level, message)`` hears of gaps."""

    def __init__(self, name: str, thermometer: Thermometer, sink: ChannelSink,
                 on_event: Callable[[str, str], None], period_s: float = PERIOD_S) -> None:  # fmt: skip
        self.name = name
        self.thermometer = thermometer
        self.sink = sink
        self.on_event = on_event
        self.period_s = period_s
        self.readings = 0
        self.failures = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"thermometer-{name}", daemon=True)

    def start(self) -> None:
        """Start reading (the first reading at once)."""
        self._thread.start()

    def _run(self) -> None:
        failing = False
        while True:
            t_asked = time.monotonic()  # the reading is from after this moment
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
                self.sink(t_asked, self.name, None, value, time.monotonic() - t_asked)
                self.readings += 1
                if failing:
                    self.on_event("info", f"{self.name} answers again ({value:.1f} C)")
                failing = False
            if self._stop.wait(max(0.0, self.period_s - (time.monotonic() - t_asked))):
                return

    def stop(self) -> None:
        """Stop reading and wait for the thread (at most one reading's timeout)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
