"""A slow switch-off says where its time went: the slowest output, when it was read back off
and how many times it had to be opened (a port a dying rig still held); the guardian that does it
asks for a CPU first."""

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


def test_the_guardian_asks_for_a_cpu_first_where_allowed() -> None:
    """Per thread on Linux: a thread raised sees its own nice value; one not allowed is left."""
    import os
    import threading

    from rig.engine.cpu_priority import GUARDIAN_NICE, raise_own_priority
    from tests.sim.nice import nice_of

    before = os.getpriority(os.PRIO_PROCESS, 0)
    seen: list[tuple[bool, int]] = []

    def probe() -> None:
        raised = raise_own_priority()
        seen.append((raised, nice_of(threading.get_native_id())))

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    raised, nice = seen[0]
    if os.geteuid() == 0:
        assert raised
    assert nice == (min(GUARDIAN_NICE, before) if raised else before)
    assert os.getpriority(os.PRIO_PROCESS, 0) == before  # per thread: the caller's unchanged
