"""A slow switch-off says where its time went: the slowest output, when it was read back off
and how many times it had to be opened (a port a dying rig still held)."""

from __future__ import annotations

from rig.engine.switch_off import SLOW_NOTE_S, OutputState, slowest_note


def state(name: str, after_s: float | None, attempts: int = 1) -> OutputState:
    return OutputState(name, False, "0.000 A read back", 0.0, done_after_s=after_s,
                       attempts=attempts)  # fmt: skip


def test_the_slowest_output_named_with_its_attempts() -> None:
    states = [state("coil_x", 0.12), state("coil_y", 1.412, attempts=3), state("heater", 0.2)]
    assert slowest_note(states) == "; slowest: coil_y read back after 1412 ms, opened at attempt 3"
    assert slowest_note([state("coil_x", 0.9)]) == "; slowest: coil_x read back after 900 ms"


def test_nothing_said_of_a_quick_or_untimed_switch_off() -> None:
    assert slowest_note([state("coil_x", SLOW_NOTE_S), state("coil_y", 0.1, attempts=2)]) == ""
    assert slowest_note([state("coil_x", None)]) == ""
    assert slowest_note([]) == ""
