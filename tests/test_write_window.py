"""How well a load channel's command times are known, as it bears on its delay (issue 30): the
writes' widths weighted by each step's share of the delay's information."""

from __future__ import annotations

import numpy as np
import pytest

from rig.analysis import write_window_s

DUT_T = np.arange(0.0, 10.0, 0.05)  # a DUT sampled at 20 Hz
RAMP_S = 0.1


def _commands(starts: list[float], widths: list[float], currents: list[float]) -> np.ndarray:
    return np.column_stack([starts, np.add(starts, widths), currents])


def test_equal_writes_give_their_width() -> None:
    cmds = _commands([1.0, 2.0, 3.0], [0.01, 0.01, 0.01], [0.5, 1.0, 0.2])
    assert write_window_s(cmds, DUT_T, RAMP_S) == pytest.approx(0.01)


def test_a_wide_write_on_a_large_step_counts_as_much_as_the_step_informs() -> None:
    # nine small steps written in 2 ms, one large step (an eclipse entry) written in 200 ms: a
    # median says 2 ms; the large step carries most of the delay's information
    starts = [0.5 + 0.9 * i for i in range(10)]
    widths = [0.002] * 9 + [0.2]
    currents = [0.1 * (i % 2) for i in range(9)] + [1.5]
    got = write_window_s(_commands(starts, widths, currents), DUT_T, RAMP_S)
    assert np.median(widths) == pytest.approx(0.002)
    assert 0.1 < got < 0.2


def test_a_write_with_no_sample_near_it_informs_nothing() -> None:
    # the wide write lies where the DUT was not sampled (left out): it does not count
    t = DUT_T[(DUT_T < 4.5) | (DUT_T > 5.5)]
    cmds = _commands([2.0, 5.0, 7.0], [0.004, 0.5, 0.004], [1.0, 0.0, 1.0])
    assert write_window_s(cmds, t, RAMP_S) == pytest.approx(0.004)


def test_no_commands_no_width() -> None:
    assert write_window_s(np.zeros((0, 3)), DUT_T, RAMP_S) == 0.0
