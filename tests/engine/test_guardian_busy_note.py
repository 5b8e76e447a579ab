"""The guardian's line says what this computer added to its time to safe: its own wait for a CPU
and the kernel's terminal layer holding serial data (a supply on a pty or USB adapter), each only
when it reached 50 ms (:func:`rig.engine.guardian_findings.busy_note`)."""

from __future__ import annotations

import time

import pytest

from rig.engine import guardian_findings as findings
from rig.engine.cpu_wait import CpuWaitLog


class Waited(CpuWaitLog):
    """A wait log that reports ``wait_s`` of CPU wait (the schedstat figures are the kernel's)."""

    def __init__(self, wait_s: float) -> None:
        super().__init__()
        self.wait_s = wait_s
        self.asked_since: float | None = None

    def waited_since(self, since: float) -> float:
        self.asked_since = since
        return self.wait_s


@pytest.mark.parametrize(
    ("cpu_s", "tty_s", "said"),
    [
        (0.0, 0.0, ""),
        (0.049, 0.049, ""),
        (0.82, 0.0, "; the guardian waited 820 ms for a CPU"),
        (0.0, 3.1, "; the terminal layer held serial data 3100 ms"),
        (
            0.3,
            1.25,
            "; the guardian waited 300 ms for a CPU; the terminal layer held serial data 1250 ms",
        ),
    ],
)
def test_busy_note_names_each_delay_worth_saying(
    monkeypatch: pytest.MonkeyPatch, cpu_s: float, tty_s: float, said: str
) -> None:
    asked: list[tuple[float, float]] = []

    def stall(since: float, until: float) -> float:
        asked.append((since, until))
        return tty_s

    monkeypatch.setattr(findings, "tty_seen_stall_s", stall)
    waits, t_found = Waited(cpu_s), time.monotonic()
    assert findings.busy_note(waits, t_found) == said
    # the CPU wait from one guardian round before it found the rig; the serial hold from then on
    assert waits.asked_since == pytest.approx(t_found - findings.CPU_WAIT_LOOKBACK_S)
    assert asked[0][0] == t_found and asked[0][1] >= t_found


def test_the_fault_harness_reads_the_cpu_wait_beside_a_terminal_note() -> None:
    from bench.faultlab import guardian_cpu_wait_ms

    line = ("rig guardian: ...; switched off coil_x in 3231 ms; the guardian waited 60 ms for a CPU;"
            " the terminal layer held serial data 3100 ms")  # fmt: skip
    assert guardian_cpu_wait_ms(line) == 60.0
