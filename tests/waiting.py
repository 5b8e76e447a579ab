"""Waiting on what a test can observe, never on the clock alone: a loaded machine (``stress-ng
--cpu 2`` beside the suite) makes every fixed sleep too short somewhere.

:func:`wait_until` polls a condition up to a generous deadline and fails naming what it waited
for; :func:`in_background` runs a scripted action (fault injection, signals) on a thread of its
own, its failure re-raised in the test by :meth:`Background.result`. Both on the process's clock
(ADR 0038): inside a simulated-time test they wait simulated seconds and the action is one of the
clock's participants, so the scenario is the same on any machine.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Generic, TypeVar

import timebase

T = TypeVar("T")


def wait_until(
    predicate: Callable[[], T], timeout_s: float, what: str, interval_s: float = 0.02
) -> T:
    """The first true value of ``predicate()``, polled every ``interval_s`` (s); an
    AssertionError naming ``what`` if none came within ``timeout_s`` (s)."""
    deadline = timebase.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if timebase.monotonic() > deadline:
            raise AssertionError(f"waited {timeout_s:g} s for {what}, in vain")
        timebase.sleep(interval_s)


class Background(Generic[T]):
    """A function running on a daemon thread; :meth:`result` joins it and returns its value or
    re-raises its exception."""

    def __init__(self, fn: Callable[[], T], name: str) -> None:
        self._fn = fn
        self._value: T | None = None
        self._error: BaseException | None = None
        self._thread = timebase.Thread(self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self._value = self._fn()
        except BaseException as exc:  # re-raised in the test's thread by result()
            self._error = exc

    def result(self, timeout_s: float = 60.0) -> T | None:
        """Wait up to ``timeout_s`` (s) for the function to end; its value, or its exception."""
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            raise AssertionError(f"{self._thread.name} still running after {timeout_s:g} s")
        if self._error is not None:
            raise self._error
        return self._value


def in_background(fn: Callable[[], T], name: str) -> Background[T]:
    """Start ``fn`` on a thread of its own (named ``name`` in failures)."""
    return Background(fn, name)
