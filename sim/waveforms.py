"""Time-continuous signals evaluated lazily at the clock's time (:mod:`timebase`: the wall clock's
monotonic seconds, or simulated time).

A :class:`FirstOrderSignal` follows piecewise-constant targets with a first-order lag
(``tau = L / R`` for a coil, a few ms for a load channel) and keeps enough history to be read at a
delayed time ``t - tau_j`` (current-to-bias delay).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass


@dataclass(frozen=True)
class _Segment:
    t0_s: float
    start: float
    target: float


class FirstOrderSignal:
    """``y(t)`` relaxing exponentially towards the latest target; thread safe.

    Args:
        tau_s: time constant (s), 0 for an instantaneous signal.
        history_s: how far back :meth:`value` can look (s).
        t0_s: time of the initial (zero) state.
    """

    def __init__(self, tau_s: float, history_s: float = 5.0, t0_s: float = 0.0) -> None:
        if tau_s < 0:
            raise ValueError("tau_s must be >= 0")
        self.tau_s = tau_s
        self.history_s = history_s
        self._segments: list[_Segment] = [_Segment(t0_s, 0.0, 0.0)]
        # a plain lock: nothing inside it waits on the clock, so in simulated time it is never
        # held while another participant runs (and it costs a tenth of the clock's own lock)
        self._lock = threading.Lock()

    def _eval(self, seg: _Segment, t_s: float) -> float:
        dt = max(t_s - seg.t0_s, 0.0)
        if self.tau_s == 0.0:
            return seg.target
        return seg.target + (seg.start - seg.target) * math.exp(-dt / self.tau_s)

    def value(self, t_s: float) -> float:
        """Signal at time ``t_s`` (may be in the recent past)."""
        with self._lock:
            for seg in reversed(self._segments):
                if seg.t0_s <= t_s:
                    return self._eval(seg, t_s)
            return self._segments[0].start

    @property
    def target(self) -> float:
        """The value the signal is relaxing towards."""
        with self._lock:
            return self._segments[-1].target

    def set_target(self, t_s: float, target: float) -> None:
        """From ``t_s`` on, relax towards ``target``."""
        with self._lock:
            last = self._segments[-1]
            start = self._eval(last, t_s)
            self._segments.append(_Segment(t_s, start, float(target)))
            cutoff = t_s - self.history_s
            while len(self._segments) > 2 and self._segments[1].t0_s < cutoff:
                self._segments.pop(0)

    def jump(self, t_s: float, value: float) -> None:
        """Set the value itself (not the target) at ``t_s``: an instantaneous step."""
        with self._lock:
            self._segments.append(_Segment(t_s, float(value), float(value)))
