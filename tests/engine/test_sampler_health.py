"""A sensor's silence is judged without the time this computer held its data back: the terminal
layer's stall and our threads' waits for a CPU, one after the other, both left out and named."""

from __future__ import annotations

import pytest

import rig.engine.sampling as sampling
from rig.engine.cpu_wait import CpuWaitLog
from rig.engine.sampling import SensorSampler


class Waited(CpuWaitLog):
    def __init__(self, waited_s: float) -> None:
        super().__init__()
        self.waited_s = waited_s

    def waited_since(self, since: float) -> float:
        return self.waited_s


def silent_sampler(last_t: float) -> SensorSampler:
    sampler = SensorSampler("reference", driver=None, sink=lambda *a: None, rate_hz=20.0)  # type: ignore[arg-type]
    sampler.started_t = 0.0
    sampler.latest = (last_t, (1.0, 2.0, 3.0))
    return sampler


@pytest.mark.parametrize(
    ("held_s", "waited_s", "judged"),
    [(0.0, 0.0, "no data for 3.0 s (stream"), (0.8, 0.8, None), (0.8, 0.0, "no data for 2.2 s"),
     (0.3, 0.2, "no data for 2.5 s beyond 0.5 s this computer held it back (terminal layer 0.3 s,"
                " waits for a CPU 0.2 s)")],
)  # fmt: skip
def test_silence_less_the_computers_share(
    monkeypatch: pytest.MonkeyPatch, held_s: float, waited_s: float, judged: str | None
) -> None:
    monkeypatch.setattr(sampling, "tty_seen_stall_s", lambda since, until=None: held_s)
    problem = silent_sampler(10.0).health(13.0, 1.5, 10, Waited(waited_s))
    if judged is None:
        assert problem is None
    else:
        assert problem is not None and judged in problem, problem
        assert problem.startswith("reference: ") and problem.endswith("check its cable and power")
