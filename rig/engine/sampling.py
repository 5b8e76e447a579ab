"""Magnetometer sampling threads: each sensor at its own rate, monotonic timestamps, into the store.

Every sample is stored with its date and how well the date is known (ADR 0020): a self-timed
stream's from :class:`rig.engine.stream_clock.StreamClock`, a polled sample's from its exchange
(taken after the request, dated at the reply).

The sampler is the only reader of its sensor. Others (the cage controller's trim) read through
:class:`BufferedSensor`, which hands out the sampler's samples as they arrive.

Its thread, waits and dates are the process's clock's (:mod:`timebase`): in simulated time the
sampler is a participant of the simulated clock and its samples are dated in simulated time.
"""

from __future__ import annotations

import contextlib
import math
from collections import deque
from collections.abc import Callable, Iterator

import timebase
from drivers.errors import (
    DeviceError,
    DeviceProtocolError,
    DeviceRefusedError,
    DeviceTimeoutError,
)
from drivers.protocols import CountsLostSamples, Magnetometer
from drivers.transport.serial_port import own_stall_s
from drivers.transport.tty_watch import tty_seen_stall_s, tty_stall_s
from rig.engine.cpu_wait import CpuWaitLog, ReadWaits
from rig.engine.stream_clock import StreamClock

Sink = Callable[[float, str, tuple[float, float, float], float], None]
"""(date s, device, reading uT, date uncertainty s): :meth:`rig.store.RunWriter.add_sample`."""
Listener = Callable[[float, tuple[float, float, float]], None]
RETRIES = 1
"""Late or unreadable replies retried in a row before a sensor is declared failed."""
RESTART_ATTEMPTS = 3
"""Tries at starting a sensor's sampling again after a pause (each with the driver's retries)."""
RESTART_WAIT_S = 15.0
"""How long :meth:`SensorSampler.paused` waits for sampling to start again (s): every attempt's
set-up exchanges timing out with their retries; a sampler still not started is then judged by
the health checks."""
WAIT_S = 0.2
"""Longest wait for a self-timed sensor's samples in one call (s): bounds how late a stop is seen."""


class SensorSampler:
    """Reads ``driver`` continuously in a thread; every sample goes to ``sink`` and to subscribers."""

    def __init__(self, name: str, driver: Magnetometer, sink: Sink, rate_hz: float = 20.0,
                 on_warning: Callable[[str], None] | None = None) -> None:  # fmt: skip
        self.name = name
        self.on_warning = on_warning
        self.retried = 0  # replies retried over the whole run
        self.driver = driver
        self.sink = sink
        self.rate_hz = rate_hz
        self.count = 0
        self.error: Exception | None = None
        self.latest: tuple[float, tuple[float, float, float]] | None = None
        self._cond = timebase.Condition()
        self._recent: deque[tuple[int, float, tuple[float, float, float], float]] = deque(
            maxlen=1000
        )  # (sequence number, date s, reading uT, date uncertainty s)
        self.listeners: list[Listener] = []
        self.started_t = timebase.monotonic()
        """When sampling started, or last started again after a pause (monotonic s)."""
        self.repeats = 0  # consecutive readings identical to the one before
        self._stop = timebase.Event()
        self._hold = timebase.Event()  # asked to let go of the sensor
        self._parked = timebase.Event()  # the thread has let go (sampling stopped)
        self._resume = timebase.Event()
        self._restarted = timebase.Event()  # clear from paused() until sampling runs again
        self._restarted.set()
        self._hold_lock = timebase.Lock()  # held while waiting for the thread to let go
        self._thread = timebase.Thread(self._run, name=f"sampler-{name}", daemon=True)

    def start(self) -> None:
        """Let the driver set the sensor up for the rate (it picks its mode and the nearest rate it
        can do), then start the thread."""
        self.rate_hz = self.driver.start_sampling(self.rate_hz)
        self.started_t = timebase.monotonic()
        self._thread.start()

    def _publish(self, t: float, xyz: tuple[float, float, float], t_unc_s: float) -> None:
        self.sink(t, self.name, xyz, t_unc_s)
        for listener in list(self.listeners):
            listener(t, xyz)
        with self._cond:
            self.count += 1
            self.repeats = (
                self.repeats + 1 if self.latest is not None and self.latest[1] == xyz else 0
            )
            self.latest = (t, xyz)
            self._recent.append((self.count, t, xyz, t_unc_s))
            self._cond.notify_all()

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        # a self-timed sensor's own clock, from the arrivals
        clock = StreamClock(period, timebase.wake_jitter_s())
        next_t = timebase.monotonic()
        failures = 0  # consecutive late or unreadable replies
        counter = self.driver if isinstance(self.driver, CountsLostSamples) else None
        waits = ReadWaits(measure=not timebase.is_simulated())
        try:
            while not self._stop.is_set():
                if self._hold.is_set():
                    self._park()
                    next_t = timebase.monotonic()
                    clock.reset()  # the stream starts again: count from its first sample
                    continue
                try:
                    if self.driver.self_timed:  # the sensor sends at its own rate
                        waits.start()
                        samples = self.driver.read_samples(WAIT_S)
                        if samples:
                            # the newest arrived when its frame's last byte had crossed the line
                            line_s = float(getattr(self.driver, "frame_line_s", 0.0))
                            lost = counter.lost_before if counter is not None else ()
                            dates = clock.dated(timebase.monotonic() - line_s, len(samples), lost)
                            late_s = waits.typical_s()  # read this late while the computer is busy
                            for (t, unc), xyz in zip(dates, samples, strict=True):
                                self._publish(t, xyz, unc + late_s)
                        failures = 0 if samples else failures
                        continue
                    next_t += period
                    asked = timebase.monotonic()
                    for xyz in self.driver.read_samples(WAIT_S):
                        # taken between the request and the reply: dated at the reply, known
                        # to within the whole exchange (a stall in it widens it)
                        replied = timebase.monotonic()
                        self._publish(replied, xyz, replied - asked)
                    failures = 0
                    self._stop.wait(max(0.0, next_t - timebase.monotonic()))
                except (DeviceTimeoutError, DeviceProtocolError) as exc:
                    # One late or garbled reply is retried: a busy line or a busy computer is
                    # not a dead sensor. The second in a row ends sampling (and the run).
                    failures += 1
                    if failures > RETRIES:
                        raise
                    self.retried += 1
                    if self.on_warning is not None:
                        self.on_warning(f"{self.name}: {exc}; read again: only what the failed"
                                        " read held is missing from the record, and a stream's"
                                        " dates start afresh from the next sample (a second"
                                        " failure in a row would have ended the run)")  # fmt: skip
                    next_t = timebase.monotonic()
                    clock.reset()  # samples may have been lost: count from the next one
        except Exception as exc:  # a device error, or a bug in a sink: never a silent end
            self.error = exc
            with self._cond:
                self._cond.notify_all()

    def _park(self) -> None:
        """Stop sampling, wait for :meth:`paused`'s caller to finish, then sample again."""
        try:
            self.driver.stop_sampling()
        finally:
            self._parked.set()
        self._resume.wait()
        self._resume.clear()
        try:
            for attempt in range(RESTART_ATTEMPTS):
                try:
                    self.rate_hz = self.driver.start_sampling(self.rate_hz)
                    break
                except (DeviceTimeoutError, DeviceProtocolError, DeviceRefusedError) as exc:
                    # the set-up exchanges on a noisy line: asked again, as the driver asks a
                    # damaged reply again; a sensor that never takes them ends sampling
                    if attempt == RESTART_ATTEMPTS - 1:
                        raise
                    if self.on_warning is not None:
                        self.on_warning(f"{self.name}: starting to sample again: {exc}; asked"
                                        " again (nothing recorded meanwhile: the step's data"
                                        " start once sampling does)")  # fmt: skip
        finally:
            self.started_t = timebase.monotonic()
            self._restarted.set()

    @property
    def pausing(self) -> bool:
        """Paused for a command (a set/reset pulse), or starting again: not judged silent."""
        return not self._restarted.is_set()

    @contextlib.contextmanager
    def paused(self, timeout_s: float = 2.0) -> Iterator[Magnetometer]:
        """The sensor's driver, not sampling, for a command its stream would get in the way of
        (a set/reset pulse); sampling starts again at the same rate afterwards. A thread that
        does not let go within ``timeout_s`` (it is stuck in a read) is a DeviceTimeoutError."""
        with self._hold_lock:
            self._parked.clear()
            self._resume.clear()
            self._restarted.clear()
            self._hold.set()
            parked = False
            try:
                parked = self._parked.wait(timeout_s)
                if not parked:
                    raise DeviceTimeoutError(
                        f"{self.name}: sampling did not pause within {timeout_s:g} s"
                    )
                yield self.driver
            finally:
                self._hold.clear()
                self._resume.set()  # (a thread that parks only now starts again at once)
                if parked:
                    # sampling has started again (or failed) before the caller goes on: what
                    # it times after the pause (a hold after a set/reset pulse) has samples
                    self._restarted.wait(RESTART_WAIT_S)
                else:  # still in its read: it goes on sampling, and is judged as before
                    self._restarted.set()

    def health(
        self, now: float, stall_s: float, stuck_after: int, cpu_wait: CpuWaitLog | None = None
    ) -> str | None:
        """What is wrong with this sensor's data, if anything: stopped, stalled or frozen.
        ``cpu_wait``: this process's threads' waits for a CPU, noted every check round."""
        if self.error is not None:
            return f"{self.name}: sampling stopped: {self.error}"
        if self.pausing:
            return None
        # silent since the newest sample, or since sampling (re)started when that was later
        last = max(self.latest[0], self.started_t) if self.latest is not None else self.started_t
        # time the kernel was seen holding serial bytes back was this computer's, not the
        # sensor's (the strict measure: a busy rig process must not postpone the verdict), and
        # so was time our threads waited for a CPU while the sensor's data sat in a buffer. The
        # two are added: one after the other they add up, and where they overlap the sum only
        # postpones the verdict on a sensor really gone by that overlap; the line names both,
        # as a stall beside two CPU hogs ("reference: no data for 2.6 s") named neither
        held_s = tty_seen_stall_s(last, now)
        ours_s = cpu_wait.waited_since(last) if cpu_wait is not None else 0.0
        silent_s = now - last - held_s - ours_s
        if silent_s > stall_s:
            computer = (f" beyond {held_s + ours_s:.1f} s this computer held it back (terminal"
                        f" layer {held_s:.1f} s, waits for a CPU {ours_s:.1f} s)"
                        if held_s + ours_s >= 0.05 else "")  # fmt: skip
            return (f"{self.name}: no data for {silent_s:.1f} s{computer} (stream stalled or"
                    " sensor disconnected); check its cable and power")  # fmt: skip
        if self.repeats >= stuck_after:
            return (f"{self.name}: the last {self.repeats + 1} readings are identical (sensor"
                    " frozen); power-cycle it")  # fmt: skip
        return None

    def caught_up(self, t: float, timeout_s: float) -> bool:
        """Wait until a sample dated at ``t`` (monotonic s) or later, less half a period, has been
        published, so that an analysis of the time up to ``t`` sees all of it: on a busy computer
        the sensor's data can sit in a buffer for a second after it was taken. False after
        ``timeout_s`` (the health checks judge a sensor that really stalled)."""
        deadline = timebase.monotonic() + timeout_s
        wanted = t - 0.5 / self.rate_hz
        with self._cond:
            while self.latest is None or self.latest[0] < wanted:
                remaining = deadline - timebase.monotonic()
                if self.error is not None or remaining <= 0:
                    return False
                self._cond.wait(remaining)
        return True

    def dated_within(self, after_s: float, before_s: float, enough: int) -> int:
        """How many of the recent samples are dated whole (date +- its uncertainty) inside
        [``after_s``, ``before_s``) (monotonic s), counted up to ``enough``."""
        found = 0
        with self._cond:
            for _, t, _, t_unc in reversed(self._recent):
                unc = 0.0 if math.isnan(t_unc) else t_unc
                if t + unc < after_s:
                    break  # older still: dates grow with the sequence
                if t - unc >= after_s and t + unc < before_s:
                    found += 1
                    if found >= enough:
                        break
        return found

    def wait_next(
        self, after: int, timeout_s: float = 2.0
    ) -> tuple[int, float, tuple[float, float, float], float]:
        """The first sample with sequence number > ``after``: (sequence number, date s, reading
        uT, date uncertainty s)."""
        start = timebase.monotonic()
        deadline = start + timeout_s
        with self._cond:
            while True:
                if self.error is not None:
                    raise DeviceError(f"{self.name}: sampling stopped: {self.error}")
                for item in self._recent:
                    if item[0] > after:
                        return item
                remaining = deadline + tty_stall_s(start) - timebase.monotonic()
                if remaining <= 0:
                    raise DeviceError(
                        f"{self.name}: no sample for {timeout_s:g} s; is it still connected?"
                    )
                t_wait = timebase.monotonic()
                self._cond.wait(remaining)
                deadline += own_stall_s(timebase.monotonic() - t_wait, remaining)

    def stop(self) -> None:
        """Stop the thread (the driver stays open)."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        with contextlib.suppress(DeviceError, OSError):
            self.driver.stop_sampling()


class BufferedSensor:
    """A sensor view for other consumers: ``read()`` returns the sampler's next sample."""

    def __init__(self, sampler: SensorSampler) -> None:
        self.sampler = sampler
        self._seen = 0
        self._not_before = -math.inf

    def flush(self) -> None:
        """Ignore everything sampled so far, including samples taken before now that have not
        arrived yet (a busy computer can hold a second of a stream back): a later :meth:`read`
        returns only a sample taken after this moment, by its date and uncertainty (ADR 0020)."""
        self._seen = self.sampler.count
        self._not_before = timebase.monotonic()

    def read(self) -> tuple[float, float, float]:
        """The next sample after the last one handed out (and taken after the last flush)."""
        while True:
            seq, t, xyz, t_unc = self.sampler.wait_next(self._seen)
            self._seen = seq
            if t - t_unc >= self._not_before:
                return xyz
