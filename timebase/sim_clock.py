"""Discrete-event simulated time (ADR 0038).

The clock's *participants* are the threads it started (:meth:`SimulatedClock.Thread`) and the
threads that :meth:`~SimulatedClock.enter` it. Exactly one participant runs at a time: it holds
the baton until it waits on the clock (``sleep``, an event, a lock, a queue, a pipe); then the
longest-ready participant runs, and when none is ready, time jumps to the earliest deadline and
the participant waiting for it runs. Simultaneous deadlines go in the order they were set, ready
participants in the order they became ready: given the same inputs, the same interleaving on any
machine and under any load. Threads outside the clock (a terminal reader, a signal) may set
events, put in queues and write to pipes at any time; they may not wait on the clock
(:class:`NotOnTheClockError`). When every participant waits with no deadline, the clock is idle
until such a thread wakes one.

Code that a participant runs must not wait on anything but this clock while another participant
could be needed to end the wait (a ``threading.Lock`` held across a wait on the clock, a join of
a plain thread): the baton would never come back. Everything the rig and the simulator wait on
comes from :mod:`timebase` for that reason.
"""

from __future__ import annotations

import heapq
import itertools
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from timebase.busy_host import BusyHost, is_host
from timebase.clock import POLL_S

PRUNE_AT = 64
"""A channel's list of waiters is cleaned of stale entries once it is this long."""


class NotOnTheClockError(RuntimeError):
    """A thread that is not a participant of the simulated clock tried to wait on it."""


class _Participant:
    __slots__ = ("deadline", "gate", "gen", "late", "name", "notified", "waiting")

    def __init__(self, name: str, late: Callable[[], float] | None = None) -> None:
        self.name = name
        self.late = late  # a busy host's delay (s) before each wake is taken (timebase.busy_host)
        self.gate = threading.Lock()
        self.gate.acquire()  # released once per turn it is given
        self.gen = 0  # one per wait: timers and channel entries of older waits are stale
        self.waiting = False
        self.notified = False
        self.deadline: float | None = None  # of the current wait (simulated s)


class Channel:
    """The participants waiting on one thing (an event, a lock, a pipe's data)."""

    __slots__ = ("_clock", "_waiters")

    def __init__(self, clock: SimulatedClock) -> None:
        self._clock = clock
        self._waiters: list[tuple[_Participant, int]] = []

    def notify(self, n: int | None = None) -> int:
        """Wake ``n`` waiters (all when None), in the order they began waiting; how many woke."""
        return self._clock._notify(self, n)


class SimulatedClock:
    """Simulated time from ``start_s`` (s); ``epoch_s``: the wall date at ``start_s`` (Unix s)."""

    simulated = True
    wake_jitter_s = 0.0
    """None: a participant runs at the simulated time it waited for (a busy host's lateness,
    :mod:`timebase.busy_host`, shows in the arrivals it delays)."""

    def __init__(self, start_s: float = 0.0, epoch_s: float | None = None) -> None:
        self._state = threading.Lock()
        self._now = float(start_s)
        self._epoch_offset = (time.time() if epoch_s is None else float(epoch_s)) - self._now
        self._ready: deque[_Participant] = deque()
        # (deadline, order, participant and the wait it ends) or (deadline, order, None, channel)
        self._timers: list[tuple[float, int, _Participant | None, Any]] = []
        self._seq = itertools.count()
        self._local = threading.local()
        self._holder: _Participant | None = None
        self._members: list[_Participant] = []
        self.switches = 0
        """Turns handed from one participant to another (a measure of the run's events)."""
        self.busy: BusyHost | None = None
        """When set, the host's threads that join from now on wake late (:mod:`timebase.busy_host`)."""

    def late_for(self, name: str, target: object) -> Callable[[], float] | None:
        """A new participant's wake delays: a busy host's for the host's threads, else none."""
        return self.busy.delays(name) if self.busy is not None and is_host(target) else None

    # --- time ----------------------------------------------------------------------------------

    def monotonic(self) -> float:
        """Simulated seconds."""
        return self._now

    def wall_time(self) -> float:
        """The simulated date (Unix s)."""
        return self._epoch_offset + self._now

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of simulated time (<= 0: after every ready participant has run)."""
        self.block((), self._now + max(float(seconds), 0.0))

    # --- participants ----------------------------------------------------------------------------

    def participant(self) -> bool:
        """Whether the calling thread is one of this clock's participants."""
        return getattr(self._local, "p", None) is not None

    def enter(self, name: str | None = None) -> None:
        """Make the calling thread a participant; returns when it has its turn."""
        if self.participant():
            raise RuntimeError("this thread is already on the simulated clock")
        p = _Participant(name or threading.current_thread().name)
        p.late = self.late_for(p.name, None)  # the thread that enters: the host's
        self._local.p = p
        with self._state:
            self._members.append(p)
            self._make_ready(p)
        self._await_turn(p)

    def leave(self) -> None:
        """The calling participant leaves the clock; the next one runs."""
        p = self._me("leaves")
        self._retire(p)
        self._local.p = None

    def members(self) -> int:
        """How many participants the clock has."""
        return len(self._members)

    def describe(self) -> list[str]:
        """One line per participant: its name and what it does (for a stalled run's report)."""
        with self._state:
            out = []
            for p in self._members:
                if p is self._holder:
                    state = "has the turn (running, or blocked outside the clock)"
                elif not p.waiting:
                    state = "ready"
                elif p.deadline is None:
                    state = "waiting, no deadline"
                else:
                    state = f"waiting until t = {p.deadline:.6f} s"
                out.append(f"{p.name}: {state}")
            if self._holder is None and not self._ready:
                out.append(
                    "(nobody has the turn: every participant waits for a thread outside the clock)"
                )
            return out

    def _me(self, what: str) -> _Participant:
        p: _Participant | None = getattr(self._local, "p", None)
        if p is None:
            raise NotOnTheClockError(
                f"thread {threading.current_thread().name!r} {what} on the simulated clock but is"
                " not one of its participants; start it with timebase.Thread"
            )
        return p

    def _admit(self, p: _Participant) -> None:
        with self._state:
            self._members.append(p)
            self._make_ready(p)

    def _retire(self, p: _Participant) -> None:
        with self._state:
            if p in self._members:
                self._members.remove(p)
            p.gen += 1
            p.waiting = False
            if self._holder is p:
                self._pass_baton()

    # --- scheduling (self._state held) -----------------------------------------------------------

    def _make_ready(self, p: _Participant) -> None:
        p.waiting = False
        if self._holder is None:
            self._holder = p
            self.switches += 1
            p.gate.release()
        else:
            self._ready.append(p)

    def _pass_baton(self) -> None:
        self._holder = None
        if self._ready:
            self._make_ready(self._ready.popleft())
            return
        while self._timers:
            deadline, _, p, gen = heapq.heappop(self._timers)
            if p is None:  # a channel's notification at its time (bytes arriving on a line)
                if deadline > self._now:
                    self._now = deadline
                if self._notify_locked(gen, None):  # the first it woke has the turn
                    return
                continue
            if p.gen == gen and p.waiting:
                if deadline > self._now:
                    self._now = deadline
                p.notified = False
                self._make_ready(p)
                return
        # nobody runnable: idle until a thread outside the clock wakes a participant

    def _notify(self, ch: Channel, n: int | None) -> int:
        with self._state:
            return self._notify_locked(ch, n)

    def _notify_locked(self, ch: Channel, n: int | None) -> int:
        woken = 0
        keep: list[tuple[_Participant, int]] = []
        for p, gen in ch._waiters:
            if p.gen != gen or not p.waiting:
                continue
            if n is not None and woken >= n:
                keep.append((p, gen))
                continue
            p.notified = True
            self._make_ready(p)
            woken += 1
        ch._waiters = keep
        return woken

    # --- waiting ---------------------------------------------------------------------------------

    def block(self, channels: Iterable[Channel], deadline: float | None) -> bool:
        """Wait until one of ``channels`` is notified (True) or simulated time reaches
        ``deadline`` (False; None: no deadline). The caller must be a participant."""
        p = self._me("waits")
        with self._state:
            p.gen += 1
            p.waiting = True
            p.notified = False
            p.deadline = deadline
            for ch in channels:
                waiters = ch._waiters
                if len(waiters) >= PRUNE_AT:
                    waiters[:] = [(q, g) for q, g in waiters if q.gen == g and q.waiting]
                waiters.append((p, p.gen))
            if deadline is not None:
                heapq.heappush(self._timers, (max(deadline, self._now), next(self._seq), p, p.gen))
            if self._holder is p:
                self._pass_baton()
        self._await_turn(p)
        notified = p.notified
        if p.late is not None:
            self._run_late(p)
        return notified

    def _run_late(self, p: _Participant) -> None:
        """A busy host takes a while to run a thread that could run (:mod:`timebase.busy_host`)."""
        delay = p.late() if p.late is not None else 0.0
        if delay <= 0.0:
            return
        late, p.late = p.late, None  # the delay itself is not delayed
        try:
            self.block((), self._now + delay)
        finally:
            p.late = late

    def _await_turn(self, p: _Participant) -> None:
        try:
            p.gate.acquire()
        except BaseException:
            # a signal's exception (Ctrl-C) while waiting for the turn: stop waiting, take the
            # next turn, and let it propagate then
            with self._state:
                if p.waiting:
                    p.gen += 1
                    p.notified = False
                    self._make_ready(p)
            while True:
                try:
                    p.gate.acquire()
                    break
                except BaseException:
                    continue
            raise

    # --- primitives ------------------------------------------------------------------------------

    def channel(self) -> Channel:
        """A new channel on this clock."""
        return Channel(self)

    def Event(self) -> Any:  # noqa: N802
        return SimEvent(self)

    def Lock(self) -> Any:  # noqa: N802
        return SimLock(self)

    def RLock(self) -> Any:  # noqa: N802
        return SimRLock(self)

    def Condition(self, lock: Any = None) -> Any:  # noqa: N802
        return SimCondition(self, lock)

    def Queue(self) -> Any:  # noqa: N802
        return SimQueue(self)

    def Thread(self, target: Callable[..., Any], *, name: str | None = None,  # noqa: N802
               args: tuple[Any, ...] = (), daemon: bool | None = None) -> threading.Thread:  # fmt: skip
        return SimThread(self, target, name=name, args=args, daemon=daemon)

    def wait_any(self, events: Sequence[threading.Event], seconds: float) -> None:
        """Wait until one of ``events`` is set or ``seconds`` of simulated time have passed (one
        turn when ``seconds`` <= 0). Events of another clock are looked at every
        :data:`~timebase.clock.POLL_S` instead."""
        if any(e.is_set() for e in events):
            return
        deadline = self._now + max(float(seconds), 0.0)
        if not all(isinstance(e, SimEvent) for e in events):
            deadline = min(deadline, self._now + POLL_S)
        channels = [e._ch for e in events if isinstance(e, SimEvent)]
        self.block(channels, deadline)

    def notify_at(self, t_s: float, ch: Channel) -> None:
        """Notify ``ch``'s waiters when simulated time reaches ``t_s`` (at once when it has): a
        write that arrives later wakes its reader then, not twice."""
        if t_s <= self._now:
            ch.notify()
            return
        with self._state:
            heapq.heappush(self._timers, (t_s, next(self._seq), None, ch))

    def deadline(self, timeout: float | None) -> float | None:
        """The simulated time ``timeout`` s from now (None stays None)."""
        return None if timeout is None else self._now + max(float(timeout), 0.0)


class SimThread(threading.Thread):
    """A participant: ready from :meth:`start` (before the real thread runs), gone when its
    target returns; :meth:`join` waits on the clock."""

    def __init__(self, clock: SimulatedClock, target: Callable[..., Any], *, name: str | None,
                 args: tuple[Any, ...], daemon: bool | None) -> None:  # fmt: skip
        super().__init__(target=target, name=name, args=args, daemon=daemon)
        self._clock = clock
        self._p = _Participant(self.name, clock.late_for(self.name, target))
        self._finished = Channel(clock)
        self._done = False

    def start(self) -> None:
        self._clock._admit(self._p)
        super().start()

    def run(self) -> None:
        clock, p = self._clock, self._p
        clock._local.p = p
        clock._await_turn(p)
        try:
            super().run()
        finally:
            self._done = True
            self._finished.notify()
            clock._retire(p)
            clock._local.p = None

    def join(self, timeout: float | None = None) -> None:
        clock = self._clock
        if not clock.participant():
            super().join(timeout)
            return
        deadline = clock.deadline(timeout)
        while not self._done:
            if deadline is not None and clock.monotonic() >= deadline:
                return
            clock.block((self._finished,), deadline)
        super().join()  # the real thread is only finishing its bookkeeping


class SimEvent:
    """:class:`threading.Event` on simulated time."""

    def __init__(self, clock: SimulatedClock) -> None:
        self._clock = clock
        self._flag = False
        self._ch = Channel(clock)

    def is_set(self) -> bool:
        return self._flag

    def set(self) -> None:
        self._flag = True
        self._ch.notify()

    def clear(self) -> None:
        self._flag = False

    def wait(self, timeout: float | None = None) -> bool:
        if self._flag:
            return True
        clock = self._clock
        deadline = clock.deadline(timeout)
        while not self.is_set():
            if deadline is not None and clock.monotonic() >= deadline:
                return False
            clock.block((self._ch,), deadline)
        return True


class SimLock:
    """:class:`threading.Lock` on simulated time: a participant waiting for it lets others run."""

    def __init__(self, clock: SimulatedClock) -> None:
        self._clock = clock
        self._owner: int | None = None
        self._ch = Channel(clock)

    def _try(self, me: int) -> bool:
        with self._clock._state:
            if self._owner is None:
                self._owner = me
                return True
            return False

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        me = threading.get_ident()
        clock = self._clock
        deadline = clock.deadline(timeout) if blocking and timeout >= 0 else None
        while not self._try(me):
            if not blocking or (deadline is not None and clock.monotonic() >= deadline):
                return False
            clock.block((self._ch,), deadline)
        return True

    def release(self) -> None:
        if self._owner is None:
            raise RuntimeError("release unlocked lock")
        self._owner = None
        if self._ch._waiters:  # (most releases have nobody waiting: no turn to hand out)
            self._ch.notify(1)

    def locked(self) -> bool:
        return self._owner is not None

    def _release_save(self) -> Any:
        self.release()
        return None

    def _acquire_restore(self, saved: Any) -> None:
        self.acquire()

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


class SimRLock(SimLock):
    """:class:`threading.RLock` on simulated time."""

    def __init__(self, clock: SimulatedClock) -> None:
        super().__init__(clock)
        self._count = 0

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        if self._owner == threading.get_ident():
            self._count += 1
            return True
        if not super().acquire(blocking, timeout):
            return False
        self._count = 1
        return True

    def release(self) -> None:
        if self._owner != threading.get_ident():
            raise RuntimeError("cannot release un-acquired lock")
        self._count -= 1
        if self._count == 0:
            super().release()

    def _release_save(self) -> Any:
        count, self._count = self._count, 0
        self._owner = None
        if self._ch._waiters:  # (most releases have nobody waiting: no turn to hand out)
            self._ch.notify(1)
        return count

    def _acquire_restore(self, saved: Any) -> None:
        SimLock.acquire(self)
        self._count = int(saved)


class SimCondition:
    """:class:`threading.Condition` on simulated time (``lock``: a lock of this clock)."""

    def __init__(self, clock: SimulatedClock, lock: Any = None) -> None:
        self._clock = clock
        self._lock = lock if lock is not None else SimRLock(clock)
        self._ch = Channel(clock)

    def acquire(self, *args: Any) -> bool:
        return bool(self._lock.acquire(*args))

    def release(self) -> None:
        self._lock.release()

    def __enter__(self) -> bool:
        return bool(self._lock.__enter__())

    def __exit__(self, *exc: object) -> None:
        self._lock.__exit__(*exc)

    def wait(self, timeout: float | None = None) -> bool:
        clock = self._clock
        deadline = clock.deadline(timeout)
        saved = self._lock._release_save()
        try:
            return clock.block((self._ch,), deadline)
        finally:
            self._lock._acquire_restore(saved)

    def wait_for(self, predicate: Callable[[], Any], timeout: float | None = None) -> Any:
        clock = self._clock
        deadline = clock.deadline(timeout)
        result = predicate()
        while not result:
            if deadline is not None:
                left = deadline - clock.monotonic()
                if left <= 0:
                    break
                self.wait(left)
            else:
                self.wait()
            result = predicate()
        return result

    def notify(self, n: int = 1) -> None:
        self._ch.notify(n)

    def notify_all(self) -> None:
        self._ch.notify()


class SimQueue:
    """An unbounded :class:`queue.Queue` on simulated time."""

    def __init__(self, clock: SimulatedClock) -> None:
        self._clock = clock
        self._items: deque[Any] = deque()
        self._ch = Channel(clock)

    def put(self, item: Any, block: bool = True, timeout: float | None = None) -> None:
        self._items.append(item)
        self._ch.notify()

    def put_nowait(self, item: Any) -> None:
        self.put(item)

    def get(self, block: bool = True, timeout: float | None = None) -> Any:
        clock = self._clock
        deadline = clock.deadline(timeout)
        while not self._items:
            if not block or (deadline is not None and clock.monotonic() >= deadline):
                raise queue.Empty
            clock.block((self._ch,), deadline)
        return self._items.popleft()

    def get_nowait(self) -> Any:
        return self.get(block=False)

    def empty(self) -> bool:
        return not self._items

    def qsize(self) -> int:
        return len(self._items)
