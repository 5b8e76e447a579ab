"""One clock for the rig, its drivers and the simulated cage (ADR 0038).

Everything that reads or waits on time asks this package, never :mod:`time` or :mod:`threading`
directly: ``timebase.monotonic()``, ``timebase.sleep(s)``, ``timebase.Event()``,
``timebase.Thread(...)``, ... They answer from the *current clock* of the process:

* :class:`WallClock` (the default): the computer's clock and :mod:`threading`'s primitives, as a
  real rig needs.
* :class:`SimulatedClock`: discrete-event simulated time. Its participants (the threads it
  started, and the thread that entered it) run one at a time; when the running one waits on the
  clock, the next ready one runs, and when none is ready time jumps to the earliest deadline. A run
  in simulated time therefore depends on neither the speed nor the load of the computer.

    with timebase.simulated() as clock:   # this thread joins the clock
        ...                               # start the simulated cage, run a procedure

A busy computer can be tried on simulated time too (:class:`BusyHost`: the host's threads wake late,
deterministically, the instruments keep time).

Byte pipes between drivers and simulated devices in simulated time are in :mod:`timebase.wires`.
"""

from timebase.busy_host import BusyHost
from timebase.clock import (
    Clock,
    Condition,
    Event,
    Lock,
    Queue,
    RLock,
    Thread,
    current,
    is_simulated,
    monotonic,
    simulated,
    sleep,
    use,
    wait_any,
    wake_jitter_s,
    wall_time,
)
from timebase.sim_clock import NotOnTheClockError, SimulatedClock
from timebase.wall import WallClock

__all__ = [
    "BusyHost",
    "Clock",
    "Condition",
    "Event",
    "Lock",
    "NotOnTheClockError",
    "Queue",
    "RLock",
    "SimulatedClock",
    "Thread",
    "WallClock",
    "current",
    "is_simulated",
    "monotonic",
    "simulated",
    "sleep",
    "use",
    "wait_any",
    "wake_jitter_s",
    "wall_time",
]
