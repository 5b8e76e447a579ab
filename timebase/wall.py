"""The wall clock: the computer's monotonic clock and :mod:`threading`'s own primitives."""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from timebase.clock import POLL_S


class WallClock:
    """Real time, for a real rig and the real-time tier of the tests."""

    simulated = False
    wake_jitter_s = 0.001
    """A scheduler's wake-up lateness on an idle computer, which arrival times cannot show
    below it (s)."""

    def monotonic(self) -> float:
        """``time.monotonic()`` (s)."""
        return time.monotonic()

    def wall_time(self) -> float:
        """``time.time()`` (Unix s)."""
        return time.time()

    def sleep(self, seconds: float) -> None:
        """``time.sleep`` (nothing for seconds <= 0)."""
        if seconds > 0:
            time.sleep(seconds)

    def wait_any(self, events: Sequence[threading.Event], seconds: float) -> None:
        """Sleep at most ``seconds`` and at most :data:`~timebase.clock.POLL_S`; at once when one
        of ``events`` is set."""
        if seconds <= 0 or any(e.is_set() for e in events):
            return
        slice_s = min(seconds, POLL_S)
        if len(events) == 1:
            events[0].wait(slice_s)
        else:
            time.sleep(slice_s)

    def Event(self) -> threading.Event:  # noqa: N802
        return threading.Event()

    def Lock(self) -> Any:  # noqa: N802
        return threading.Lock()

    def RLock(self) -> Any:  # noqa: N802
        return threading.RLock()

    def Condition(self, lock: Any = None) -> threading.Condition:  # noqa: N802
        return threading.Condition(lock)

    def Queue(self) -> queue.Queue[Any]:  # noqa: N802
        return queue.Queue()

    def Thread(self, target: Callable[..., Any], *, name: str | None = None,  # noqa: N802
               args: tuple[Any, ...] = (), daemon: bool | None = None) -> threading.Thread:  # fmt: skip
        return threading.Thread(target=target, name=name, args=args, daemon=daemon)
