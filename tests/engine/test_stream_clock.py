"""A self-timed stream's samples dated by the sensor's own clock, recovered from their arrivals:
read in bursts by a computer that stalls (as under a CPU hog), each sample's date stays within a
few ms of when it was taken, where dating a burst back from the moment it was read puts samples
up to a period late; the period is found when the sensor runs off its nominal rate."""

from __future__ import annotations

import numpy as np
import pytest

from rig.engine.stream_clock import StreamClock

LATENCY_S = 0.003  # the shortest transmission time: the envelope's own offset


def stalled_reads(
    seed: int, period_s: float, duration_s: float
) -> tuple[np.ndarray, list[tuple[float, int]]]:
    """True sample times, and the reads (time, samples read) of a reader that wakes 0-0.5 ms after
    data arrive, except in stalls of 0.2-1.2 s starting every 2 s on average (a busy computer):
    what arrived during a stall is read at its end, as one burst."""
    rng = np.random.default_rng(seed)
    sent = 100.0 + period_s * np.arange(int(duration_s / period_s))
    arrived = sent + LATENCY_S + rng.exponential(0.001, sent.size)
    starts = 100.0 + np.cumsum(rng.exponential(2.0, int(duration_s)))
    stalls = np.column_stack([starts, starts + rng.uniform(0.2, 1.2, starts.size)])
    read = arrived + rng.uniform(0.0, 0.0005, sent.size)
    for t0, t1 in stalls:
        read[(read >= t0) & (read < t1)] = t1
    read = np.maximum.accumulate(read)  # one reader: in order
    times, counts = np.unique(read, return_counts=True)
    return sent, [(float(t), int(n)) for t, n in zip(times, counts, strict=True)]


@pytest.mark.parametrize("rate_error", [0.0, 4e-4, -0.01])
def test_dates_stay_within_a_few_ms_through_stalls(rate_error: float) -> None:
    nominal = 0.05
    sent, reads = stalled_reads(1, nominal * (1 + rate_error), 300.0)
    clock = StreamClock(nominal)
    dated, backdated, arrival = [], [], []
    for t_read, n in reads:
        dated += clock.date(t_read, n)
        backdated += [t_read - (n - 1 - j) * nominal for j in range(n)]  # the old way
        arrival += [t_read] * n
    dated_a, old = np.array(dated), np.array(backdated)
    late = dated_a - (sent + LATENCY_S)
    settled = sent > 100.0 + 30.0  # the period is fitted after a few blocks
    assert np.all(dated_a <= np.array(arrival)) and np.all(np.diff(dated_a) > 0)
    assert np.abs(late[settled]).max() < 0.005, np.abs(late[settled]).max()
    assert clock.period_s == pytest.approx(nominal * (1 + rate_error), rel=2e-5)
    # what it fixes: bursts dated back from the read are up to a period late
    old_late = old - (sent + LATENCY_S)
    assert old_late[settled].max() > 0.03
    print(f"rate error {rate_error:+.1e}: worst |date error| {1000 * np.abs(late[settled]).max():.1f}"
          f" ms, back-dated bursts {1000 * old_late[settled].max():.1f} ms")  # fmt: skip


def test_a_reset_forgets_the_old_stream() -> None:
    clock = StreamClock(0.05)
    clock.date(10.0, 3)
    clock.reset()
    assert clock.date(50.0, 2) == [pytest.approx(49.95), 50.0]


@pytest.mark.parametrize("rate_error", [0.0, 4e-4, -0.01, 0.03, -0.045])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_every_date_is_within_its_stated_uncertainty(seed: int, rate_error: float) -> None:
    """The uncertainty is a promise: every sample was taken within date +- uncertainty, from the
    first sample on (the period not yet fitted) and through every stall; on time it is about a
    millisecond, and only samples a stall delayed are known less well."""
    nominal = 0.05
    sent, reads = stalled_reads(seed, nominal * (1 + rate_error), 120.0)
    clock = StreamClock(nominal)
    out: list[tuple[float, float]] = []
    for t_read, n in reads:
        out += clock.dated(t_read, n)
    dated = np.array(out)
    error = dated[:, 0] - (sent + LATENCY_S)
    unc = dated[:, 1]
    assert np.all(np.abs(error) <= unc), np.max(np.abs(error) / unc)
    fitted = sent > 100.0 + 30.0
    assert np.median(unc[fitted]) < 0.002
    assert np.quantile(unc[fitted], 0.99) < 0.005
    print(f"seed {seed} rate error {rate_error:+.1e}: worst |error|/uncertainty"
          f" {np.max(np.abs(error) / unc):.2f}, median uncertainty {1000 * np.median(unc):.2f} ms,"
          f" largest {1000 * unc.max():.0f} ms")  # fmt: skip
