"""A flush of the buffered reference view drops samples taken before it even when they arrive
after it: on a busy computer a stream is read a second late, and the cage characterization and
trim then averaged readings from before the current changed (issue 30, ADR 0020)."""

from __future__ import annotations

import time
from typing import Any

from rig.engine.sampling import BufferedSensor


class LateStream:
    """A sampler stand-in whose samples arrive after the flush, some taken before it."""

    def __init__(self, items: list[tuple[float, tuple[float, float, float], float]]) -> None:
        self.count = 0
        self.items = items

    def wait_next(self, after: int, timeout_s: float = 2.0) -> tuple[Any, ...]:
        t, xyz, unc = self.items[after]
        return after + 1, t, xyz, unc


def test_samples_dated_before_the_flush_are_skipped_when_they_arrive_late() -> None:
    now = time.monotonic()
    old, new = (1.0, 0.0, 0.0), (2.0, 0.0, 0.0)
    stream = LateStream([
        (now - 0.30, old, 0.001),   # taken before the flush, arrives after it
        (now - 0.01, old, 0.001),
        (now + 0.02, old, 0.05),    # dated after the flush but perhaps taken before: skipped
        (now + 0.10, new, 0.002),
        (now + 0.15, new, 0.002),
    ])  # fmt: skip
    view = BufferedSensor(stream)  # type: ignore[arg-type]
    view.flush()
    assert [view.read(), view.read()] == [new, new]
