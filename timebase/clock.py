"""The clock protocol and the process's current clock (the module-level functions ask it)."""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

if TYPE_CHECKING:
    from timebase.busy_host import BusyHost

T = TypeVar("T")


class Clock(Protocol):
    """What every clock offers. Times in seconds; ``monotonic`` never goes back."""

    simulated: bool
    wake_jitter_s: float
    """How late (s) a thread of this clock may wake, or read what arrived, with no sign of it in
    what it measures: the least date uncertainty a timing claims (a floor under what arrivals
    show)."""

    def monotonic(self) -> float:
        """Seconds on this clock (an arbitrary origin)."""
        ...

    def wall_time(self) -> float:
        """Seconds since the Unix epoch (for dates people read: the store's, the report's)."""
        ...

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` (<= 0: let others run, then go on)."""
        ...

    def wait_any(self, events: Sequence[threading.Event], seconds: float) -> None:
        """Wait at most ``seconds``, returning early once one of ``events`` is set. It may also
        return early for no reason (the wall clock returns within :data:`POLL_S`): callers
        look at what they wait for and wait again."""
        ...

    def Event(self) -> threading.Event:  # noqa: N802 - the threading name it stands for
        """An event as :class:`threading.Event`."""
        ...

    def Lock(self) -> Any:  # noqa: N802
        """A lock as :class:`threading.Lock` (safe to hold while waiting on this clock)."""
        ...

    def RLock(self) -> Any:  # noqa: N802
        """A re-entrant lock as :class:`threading.RLock`."""
        ...

    def Condition(self, lock: Any = None) -> threading.Condition:  # noqa: N802
        """A condition variable as :class:`threading.Condition`."""
        ...

    def Queue(self) -> queue.Queue[Any]:  # noqa: N802
        """An unbounded FIFO queue as :class:`queue.Queue`."""
        ...

    def Thread(self, target: Callable[..., Any], *, name: str | None = None,  # noqa: N802
               args: tuple[Any, ...] = (), daemon: bool | None = None) -> threading.Thread:  # fmt: skip
        """A thread as :class:`threading.Thread`; on a simulated clock, a participant."""
        ...


POLL_S = 0.05
"""The longest a wall-clock :func:`wait_any` waits before it returns to be asked again (s): the
wall clock waits on one event at a time, so it looks at several this often."""

_current: Clock | None = None
_lock = threading.Lock()


def current() -> Clock:
    """The process's clock (the wall clock unless :func:`use` set another)."""
    global _current
    if _current is None:
        from timebase.wall import WallClock

        with _lock:
            if _current is None:
                _current = WallClock()
    return _current


@contextlib.contextmanager
def use(clock: Clock) -> Iterator[Clock]:
    """Make ``clock`` the process's clock inside the block (the previous one after it)."""
    global _current
    before = current()
    _current = clock
    try:
        yield clock
    finally:
        _current = before


STALL_REPORT_S = 120.0
"""Wall seconds without a hand-over after which a simulated clock reports a stall."""


@contextlib.contextmanager
def simulated(
    start_s: float = 0.0,
    epoch_s: float | None = None,
    stall_report_s: float | None = STALL_REPORT_S,
    busy: BusyHost | None = None,
) -> Iterator[Any]:
    """A fresh :class:`~timebase.simulated.SimulatedClock` as the process's clock, with the
    calling thread as its first participant; on leaving, the thread leaves it. ``epoch_s`` is
    the wall date (Unix s) at ``start_s`` (default: now). Its threads run on one CPU
    (:mod:`timebase.one_cpu`: a tenth of the cost per hand-over). When no participant gets the turn for
    ``stall_report_s`` wall seconds, what each waits for and every stack go to standard error
    (:mod:`timebase.stall_watch`; None: no watch). ``busy``: the host's threads wake late, as
    on a busy computer (:mod:`timebase.busy_host`; the instruments' never)."""
    from timebase.one_cpu import one_cpu
    from timebase.sim_clock import SimulatedClock
    from timebase.stall_watch import StallWatch

    clock = SimulatedClock(start_s=start_s, epoch_s=epoch_s)
    clock.busy = busy
    watch = None if stall_report_s is None else StallWatch(clock, stall_report_s)
    with one_cpu(), use(clock):
        clock.enter()
        try:
            yield clock
        finally:
            clock.leave()
            if watch is not None:
                watch.stop()


def is_simulated() -> bool:
    """Whether the process runs on simulated time."""
    return bool(current().simulated)


def monotonic() -> float:
    """Seconds on the current clock."""
    return current().monotonic()


def wake_jitter_s() -> float:
    """The current clock's unseen wake-up lateness (s): :attr:`Clock.wake_jitter_s`."""
    return float(current().wake_jitter_s)


def wall_time() -> float:
    """The date on the current clock (Unix s)."""
    return current().wall_time()


def sleep(seconds: float) -> None:
    """Wait ``seconds`` on the current clock."""
    current().sleep(seconds)


def wait_any(events: Sequence[threading.Event], seconds: float) -> None:
    """Wait at most ``seconds`` on the current clock, returning early once one of ``events`` is
    set (or, on the wall clock, within :data:`POLL_S`): loop on what is awaited."""
    current().wait_any(events, seconds)


def Event() -> threading.Event:  # noqa: N802
    """A :class:`threading.Event` of the current clock."""
    return current().Event()


def Lock() -> Any:  # noqa: N802
    """A lock of the current clock (hold it across waits on the clock: others wait on it)."""
    return current().Lock()


def RLock() -> Any:  # noqa: N802
    """A re-entrant lock of the current clock."""
    return current().RLock()


def Condition(lock: Any = None) -> threading.Condition:  # noqa: N802
    """A condition variable of the current clock."""
    return current().Condition(lock)


def Queue() -> queue.Queue[Any]:  # noqa: N802
    """A FIFO queue of the current clock (``queue.Empty`` on a timeout, as the standard one)."""
    return current().Queue()


def Thread(target: Callable[..., Any], *, name: str | None = None,  # noqa: N802
           args: tuple[Any, ...] = (), daemon: bool | None = None) -> threading.Thread:  # fmt: skip
    """A thread of the current clock (on a simulated clock, one of its participants)."""
    return current().Thread(target, name=name, args=args, daemon=daemon)
