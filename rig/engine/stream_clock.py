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

A frame lost without a trace (no byte of it arrived) numbers every sample after it short. A
read's newest sample cannot be later on the envelope than the next one's arrival, so whole
periods of lateness are lost samples (:data:`NEXT_LATE`): the read's dates widen by the periods
in doubt, and the next read, as late, confirms the loss and the stream is numbered past it; a
single late read (a busy computer) is none. The period is fitted through the newest block minima
that lie on one line (:data:`STEP_BLOCK`: a loss not seen when it happened steps them).
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
FIT_BOUND = (235.8, 19.21, 9.22, 6.62, 5.51, 4.90, 4.53, 4.28, 4.09, 3.96, 3.85, 3.76, 3.69, 3.64,
             3.59, 3.54, 3.51, 3.48, 3.45, 3.42, 3.40, 3.38)  # fmt: skip
"""A fitted period's uncertainty is taken as this many standard errors of the fit (a bound): the
Student t quantile of 3 sigma (99.865 %) for the fit's 1, 2, ... degrees of freedom (three
standard errors of a line through three block minima, one dof, had claimed 0.57 % where the
period was 1.8 % off)."""
NEXT_LATE = 0.25
"""An unseen loss (a frame that never arrived, so no byte says it was lost) shows in how late a
read's newest sample arrived on the envelope: the next sample had not arrived when it was read,
so without a loss it is late by less than a period plus how late that next one may be, at most
this fraction of a period. Later by whole periods than that, as many samples were lost (or the
stream paused: the same to the arrivals); within the arrivals' jitter of a whole period, perhaps
one was. Either way the read's dates widen by the periods in doubt, and the next read, as late,
confirms the loss: it and the stream are numbered past it. A single late read (a busy computer)
is no loss: the next one is on time."""
STEP_BLOCK = 0.5
"""Block minima this many periods or more off the line through them do not lie on one line: a
loss not seen when it happened (before the period was known well enough to count periods by)
numbered every sample after it short, a step of whole periods. The period is fitted through the
newest blocks that do lie on one line."""
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
        self._doubt = (0, 0)  # periods the last read's newest may be numbered short by (lo, hi)
        self.unseen_lost = 0
        """Samples found lost by their arrivals (none said so; negative: a loss was said that
        the arrivals deny)."""

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
        # how much wider each date is: a sample that may be numbered a loss away from its own
        ks, widen = self._late_newest(ks, arrival_s, first)
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
        for k, wider in zip(ks, widen, strict=True):
            t = min(arrival_s, k * self.period_s + c)
            if self._last_t is not None:
                t = max(t, min(arrival_s, self._last_t + 1e-6))
            self._last_t = t
            # the date's sensitivity to the period within its uncertainty
            reach = max(abs(min(arrival_s, k * q + c_q) - t) for q, c_q in bounds)
            out.append((t, jitter + reach + wider))
        return out

    def _late_newest(self, ks: list[int], arrival_s: float,
                     first: int) -> tuple[list[int], list[float]]:  # fmt: skip
        """The numbers ``ks`` of a read's samples (oldest first) corrected by the read before,
        and how much wider (s) each date is to be, from how late the read's newest sample arrived
        on the envelope (:data:`NEXT_LATE`). Whole periods late, samples were lost unseen before
        it (or the stream paused: the same to the arrivals): the read's samples keep their
        numbers (a sample numbered short sits above the envelope, never below it) and their
        dates widen by the periods in doubt; the next read, as late, confirms the loss and it
        and the stream are numbered past it (issue 54: unseen losses in a stream read in bursts
        had misdated the samples after them by 22-97 times their dates' width)."""
        was_lo, was_hi = self._doubt
        self._doubt = (0, 0)
        if len(self._recent) < MIN_ARRIVALS or not self._low:
            return ks, [0.0] * len(ks)
        p = self.period_s
        c = self._residual(self._low[0])
        delta = self.rate_uncertainty if self._fitted else self._early_rate_uncertainty()
        slack = self._jitter_s(c) + abs(ks[-1] - self._low[0][0]) * p * delta
        late = arrival_s - (ks[-1] * p + c)
        if slack > NEXT_LATE * p:  # the period is not known well enough to count periods by:
            hi = max(was_hi, math.floor((late + slack) / p))  # as many as it might be
            self._doubt = (was_lo, hi)
            return ks, [hi * p] * len(ks)
        if late + slack < 0:  # before its number's time: a loss was said that was none
            back = max(math.floor((late + slack) / p) + 1, first - ks[0])
            self._k += back
            self.unseen_lost += back
            return [k + back for k in ks], [0.0] * len(ks)
        seen = math.floor((late + slack) / p)  # periods this read's newest may be late by
        base = min(was_hi, seen) if was_hi and seen >= max(was_lo, 1) else 0  # confirmed
        self._k += base
        self.unseen_lost += base
        late -= base * p
        lo = max(0, math.floor((late - NEXT_LATE * p) / p))
        hi = max(lo, math.floor((late + slack) / p))
        self._doubt = (lo, hi)
        return [k + base for k in ks], [hi * p] * len(ks)

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
        line = _newest_line(list(self._blocks))
        if line is None or abs(line[0] / self.nominal_s - 1.0) > MAX_RATE_ERROR:
            return
        if line[1] >= MAX_RATE_ERROR:  # no better than not fitted
            return
        self.period_s, self.rate_uncertainty = line
        self._fitted = True
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


def _newest_line(blocks: list[tuple[int, float]]) -> tuple[float, float] | None:
    """:func:`_line` through the most blocks, newest first, that lie on one line (every one
    within :data:`STEP_BLOCK` of a period of it), at least three; None when the newest three do
    not."""
    for start in range(len(blocks) - 2):
        part = blocks[start:]
        line = _line(part)
        if line is None:
            continue
        k0 = sum(j for j, _ in part) / len(part)
        t0 = sum(a for _, a in part) / len(part)
        if all(abs(a - t0 - line[0] * (j - k0)) < STEP_BLOCK * line[0] for j, a in part):
            return line
    return None


def _line(points: list[tuple[int, float]]) -> tuple[float, float] | None:
    """Least-squares period (s) through (sample number, time s) points, and its relative
    uncertainty (:data:`FIT_BOUND` standard errors, at least :data:`MIN_RATE_UNCERTAINTY`);
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
    dof = len(ks) - 2
    scatter /= max(1, dof)
    bound = FIT_BOUND[min(max(dof, 1), len(FIT_BOUND)) - 1]
    return slope, max(MIN_RATE_UNCERTAINTY, bound * math.sqrt(scatter / sxx) / slope)
