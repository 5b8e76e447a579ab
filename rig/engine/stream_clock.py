"""When a self-timed sensor took each sample: its own clock, recovered from arrival times.

A streaming sensor (the HMR2300 in continuous mode, an ASCII fluxgate) sends sample ``k`` at
``s0 + k p`` by its own oscillator. The rig sees each sample arrive later than that by the
transmission time and by however long this process took to read it: on a busy computer a stream
is read in bursts, and a burst dated back from the moment it was read puts every sample in it up
to one period late (50 ms at 20 Hz), which moves a delay estimate by as much.

The arrivals' lower envelope is the sensor's clock plus the shortest transmission time: an
arrival can be late, never early. So sample ``k`` is dated ``min(a_k, min_j (a_j + (k - j) p))``
over the arrivals ``a_j`` of the last :data:`WINDOW_S`, with the period ``p`` itself taken from
the envelope's slope over a longer baseline (a crystal is off its nominal rate by up to a few
hundred ppm; a sensor that runs at its own idea of a rate by more). A sample is never dated
after its arrival, and dates never go backwards.

Each date comes with how well it is known (:meth:`StreamClock.dated`, s, a half-width): the
envelope's own jitter (how far the lowest tenth of the arrivals sits above the lowest) plus how
far the date moves when the period takes either end of its uncertainty (until the period is fitted, how far a line through the window's
lowest arrivals is from the nominal period, plus that line's uncertainty; then three standard
errors of the fit): a
sample dated by extrapolation from an arrival many periods away is known less well. A stall or a burst therefore widens the uncertainty of the samples it delayed instead of
shifting their dates (ADR 0020).
"""

from __future__ import annotations

import math
from collections import deque

WINDOW_S = 5.0
"""The envelope looks this far back (s): longer than any stall of a busy computer (1-2 s seen),
short enough that a period error of 0.1 % shifts dates by at most 5 ms."""
BLOCK_S = 5.0
"""The period is fitted through the lowest point of each block of this length (s) ..."""
BLOCKS = 24
"""... over the last this many blocks (2 minutes)."""
MAX_RATE_ERROR = 0.05
"""A fitted period further than this (relative) from the nominal one is not believed: the nominal
period is kept (a stream that stopped and restarted, not a slow oscillator)."""
JITTER_FLOOR_S = 0.001
"""The smallest date uncertainty claimed by default (s): the scheduler's wake-up jitter on an idle
computer (the sampler passes its clock's, :func:`timebase.wake_jitter_s`: none on simulated
time, where a 1 ms floor made an idle frequency response's phase sigmas 30 times the errors)."""
EARLY_BLOCK_S = 0.5
"""Before the period is fitted, its uncertainty comes from the lowest arrival of each this long
(s) in the window."""
MIN_ARRIVALS = 10
"""Below this many arrivals in the window the envelope is not yet known: dates +- a period."""
FIT_SIGMAS = 3.0
"""A fitted period's uncertainty is taken as this many standard errors of the fit (a bound)."""
TIGHT_BATCHES = 10
"""An unseen loss (a frame that never arrived, so no byte says it was lost) is recognised only
in a tight stream: single samples whose arrivals, the last this many, sat within
:data:`TIGHT_SPREAD` of a period of each other above the sensor's clock ..."""
TIGHT_SPREAD = 0.25
"""... (a fraction of the period); then one arriving more than :data:`LOSS_JUMP` of a period
later than they did was preceded by lost samples (as many periods as it is late). A stream read
in bursts by a busy computer is never tight: there a loss only widens the dates' uncertainty."""
LOSS_JUMP = 0.5
MIN_RATE_UNCERTAINTY = 1e-5
"""A fitted period is never claimed better than this (relative): a crystal's short-term wander."""


class StreamClock:
    """Dates the samples of one self-timed stream (the ``k``-th sample since :meth:`reset`) from
    their arrival times (monotonic s) and the sensor's nominal period (s)."""

    def __init__(self, period_s: float, floor_s: float = JITTER_FLOOR_S) -> None:
        self.nominal_s = period_s
        self.floor_s = floor_s
        """The smallest date uncertainty claimed (s): how late a read may be unseen."""
        self.reset()

    def reset(self) -> None:
        """A new stream (started, or resumed after samples were lost): forget the envelope."""
        self.period_s = self.nominal_s
        self.rate_uncertainty = MAX_RATE_ERROR  # relative, of the fitted period
        self._fitted = False
        self._k = 0
        self._last_t: float | None = None
        self._recent: deque[tuple[int, float]] = deque()  # (j, a_j) within WINDOW_S
        # the sliding-window minimum of r_j = a_j - j p: a subsequence of _recent whose
        # residuals increase from front to back, so the front is the minimum
        self._low: deque[tuple[int, float]] = deque()
        self._blocks: deque[tuple[int, float]] = deque(maxlen=BLOCKS)  # lowest (j, a_j) per block
        self._block_start: float | None = None
        self._block_low: tuple[int, float] | None = None
        self._arrivals: deque[float] = deque(maxlen=TIGHT_BATCHES)  # residuals of single samples
        self._suspected = 0  # periods the last single sample arrived late by, not yet confirmed
        self._tight_residual = 0.0  # the tight arrivals' mean residual it was late against (s)
        self.unseen_lost = 0
        """Samples found lost by their arrival in a tight stream (none said so; negative: a
        loss was said that the arrivals deny)."""

    def _residual(self, point: tuple[int, float]) -> float:
        return point[1] - point[0] * self.period_s

    def _push(self, point: tuple[int, float]) -> None:
        r = self._residual(point)
        while self._low and self._residual(self._low[-1]) >= r:
            self._low.pop()
        self._low.append(point)

    def date(self, arrival_s: float, n: int = 1) -> list[float]:
        """When the next ``n`` samples of the stream were taken (monotonic s), all read at
        ``arrival_s`` (a burst: the whole burst shapes the envelope before any is dated)."""
        return [t for t, _ in self.dated(arrival_s, n)]

    def dated(self, arrival_s: float, n: int = 1,
              lost_before: tuple[int, ...] = ()) -> list[tuple[float, float]]:  # fmt: skip
        """(date s, uncertainty s) of the next ``n`` samples, all read at ``arrival_s``: each
        sample was taken within date +- uncertainty on the sensor's clock (as offset by the
        shortest transmission time, common to the whole stream). ``lost_before[i]``: samples
        the sensor sent that were lost just before sample ``i`` (they keep their numbers)."""
        first = self._k  # the number after the last sample dated
        ks = []
        for i in range(n):
            self._k += lost_before[i] if i < len(lost_before) else 0
            ks.append(self._k)
            self._k += 1
        widen = 0.0  # a single sample that may be numbered a loss away from its own
        if n == 1:
            k, widen = self._unseen_loss(ks[0], arrival_s, first)
            ks = [k]
        else:
            self._arrivals.clear()
            self._suspected = 0
        for k in ks:
            point = (k, arrival_s)
            self._note_block(point)
            self._recent.append(point)
            self._push(point)
        horizon = arrival_s - WINDOW_S
        while self._recent[0][1] < horizon:
            self._recent.popleft()
        while self._low[0][1] < horizon:
            self._low.popleft()
        c = self._residual(self._low[0])
        jitter = self._jitter_s(c)
        delta = self.rate_uncertainty if self._fitted else self._early_rate_uncertainty()
        bounds = [
            (q, min(a - j * q for j, a in self._recent))
            for q in (self.period_s * (1 - delta), self.period_s * (1 + delta))
        ]
        out = []
        for k in ks:
            t = min(arrival_s, k * self.period_s + c)
            if self._last_t is not None:
                t = max(t, min(arrival_s, self._last_t + 1e-6))
            self._last_t = t
            # the date's sensitivity to the period within its uncertainty
            reach = max(abs(min(arrival_s, k * q + c_q) - t) for q, c_q in bounds)
            out.append((t, jitter + reach + widen))
        return out

    def _unseen_loss(self, k: int, arrival_s: float, first: int) -> tuple[int, float]:
        """The number of a single sample read at ``arrival_s`` (counted ``k``, at least
        ``first``), corrected by its arrival in a tight stream (see :data:`TIGHT_BATCHES`), and
        how much wider (s) its date is to be. Whole periods later than the last ones, samples
        were lost unseen; earlier, a loss was counted that was none. One such arrival is only a
        suspicion (a busy computer reads a sample late as often): its date keeps its number,
        widened by the periods in doubt; the next arrival confirms the loss (it is as late) and
        is numbered past it, or clears the suspicion (issue 54: unconfirmed, late reads on a
        busy host renumbered the stream and bent the fitted period by 300 ppm)."""
        p = self.period_s
        recent = self._arrivals
        suspected, self._suspected = self._suspected, 0
        if suspected:  # as late as the one before, against the same tight arrivals: confirmed
            late = arrival_s - k * p - self._tight_residual
            if abs(late - suspected * p) < LOSS_JUMP * p:
                self._k += suspected
                self.unseen_lost += suspected
                return k + suspected, 0.0
        if len(recent) == TIGHT_BATCHES and max(recent) - min(recent) < TIGHT_SPREAD * p:
            self._tight_residual = sum(recent) / len(recent)
            late = arrival_s - k * p - self._tight_residual
            shift = max(round(late / p), first - k) if abs(late) > LOSS_JUMP * p else 0
            if shift:  # suspected: the same number, its date as wide as the loss would move it
                self._suspected = shift
                return k, abs(shift) * p
        recent.append(arrival_s - k * p)
        return k, 0.0

    def _jitter_s(self, envelope_s: float) -> float:
        """How far the lowest tenth of the window's arrivals sits above the envelope (s), at
        least :attr:`floor_s`: a bound on how late the anchoring arrival itself may have been."""
        excess = sorted(self._residual(p) - envelope_s for p in self._recent)
        if len(excess) < MIN_ARRIVALS:  # too few to know the envelope: a period either way
            return max(self.floor_s, self.period_s)
        return max(self.floor_s, excess[len(excess) // 10])

    def _note_block(self, point: tuple[int, float]) -> None:
        """Keep each block's lowest point; refit the period when a block closes."""
        if self._block_start is None:
            self._block_start = point[1]
        if point[1] - self._block_start >= BLOCK_S and self._block_low is not None:
            self._blocks.append(self._block_low)
            self._block_start, self._block_low = point[1], None
            self._refit()
        if self._block_low is None or self._residual(point) < self._residual(self._block_low):
            self._block_low = point

    def _refit(self) -> None:
        """The period from the blocks' lowest points: a least-squares line through the block
        minima (each within a few ms of the envelope); the window minimum is then rebuilt."""
        if len(self._blocks) < 3:
            return
        line = _line(list(self._blocks))
        if line is None or abs(line[0] / self.nominal_s - 1.0) > MAX_RATE_ERROR:
            return
        self.period_s, self.rate_uncertainty = line
        self._fitted = True
        self._arrivals.clear()  # their residuals were taken with the old period
        self._low.clear()
        for point in self._recent:
            self._push(point)

    def _early_rate_uncertainty(self) -> float:
        """Before the period is fitted: how far the nominal period may be from the sensor's
        (relative), from a line through the lowest arrival of each :data:`EARLY_BLOCK_S` of the
        window - its distance from the nominal plus its own uncertainty - capped at
        :data:`MAX_RATE_ERROR` (also what is claimed with too few arrivals for a line)."""
        lows: dict[int, tuple[int, float]] = {}
        t0 = self._recent[0][1]
        for point in self._recent:
            b = int((point[1] - t0) / EARLY_BLOCK_S)
            if b not in lows or self._residual(point) < self._residual(lows[b]):
                lows[b] = point
        line = _line(list(lows.values())) if len(lows) >= 4 else None
        if line is None:
            return MAX_RATE_ERROR
        slope, unc = line
        return min(MAX_RATE_ERROR, abs(slope / self.period_s - 1.0) + unc)


def _line(points: list[tuple[int, float]]) -> tuple[float, float] | None:
    """Least-squares period (s) through (sample number, time s) points, and its relative
    uncertainty (:data:`FIT_SIGMAS` standard errors, at least :data:`MIN_RATE_UNCERTAINTY`);
    None when the points do not determine a positive slope."""
    ks = [float(j) for j, _ in points]
    ts = [a for _, a in points]
    k_mean, t_mean = sum(ks) / len(ks), sum(ts) / len(ts)
    sxx = sum((k - k_mean) ** 2 for k in ks)
    if sxx <= 0:
        return None
    slope = sum((k - k_mean) * (t - t_mean) for k, t in zip(ks, ts, strict=True)) / sxx
    if slope <= 0:
        return None
    scatter = sum((t - t_mean - slope * (k - k_mean)) ** 2 for k, t in zip(ks, ts, strict=True))
    scatter /= max(1, len(ks) - 2)
    return slope, max(MIN_RATE_UNCERTAINTY, FIT_SIGMAS * math.sqrt(scatter / sxx) / slope)
