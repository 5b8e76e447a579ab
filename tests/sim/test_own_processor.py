"""The simulated instruments' threads run at a raised priority where the system allows it
(sim.own_processor): a busy computer delays the rig, not the instruments it simulates."""

from __future__ import annotations

import os
import threading

import pytest

import timebase
from sim.cage import SimulatedCage
from sim.config import load_config
from sim.own_processor import INSTRUMENT_NICE, instrument_priority
from tests.sim.nice import nice_of

pytestmark = pytest.mark.realtime


def allowed() -> bool:
    """Whether this process may lower a nice value (root or CAP_SYS_NICE)."""
    with instrument_priority() as raised:
        return raised


def test_the_cage_threads_run_at_an_instruments_priority_and_the_caller_keeps_its_own() -> None:
    caller = threading.get_native_id()
    own = nice_of(caller)  # the suite may run niced (nice -n 5 pytest)
    before = {t.native_id for t in threading.enumerate()}
    cage = SimulatedCage(load_config())
    cage.start()
    try:
        started = [t for t in threading.enumerate() if t.native_id not in before]
        assert {t.name for t in started} >= {"dut", "reference", "sim-modbus"}
        expected = INSTRUMENT_NICE if allowed() else own
        assert cage.own_processor is allowed()
        assert {t.name: nice_of(t.native_id or 0) for t in started} == {
            t.name: expected for t in started
        }
        assert nice_of(caller) == own  # the test's own thread is back where it was
    finally:
        cage.stop()


def test_where_the_system_refuses_the_devices_start_as_before(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def refuse(which: int, who: int, value: int) -> None:
        raise PermissionError(13, "Permission denied")  # setpriority(2) without CAP_SYS_NICE

    own = nice_of(threading.get_native_id())
    monkeypatch.setattr(os, "setpriority", refuse)
    cage = SimulatedCage(load_config())
    cage.start()
    try:
        assert cage.own_processor is False
        sim_threads = [t for t in threading.enumerate() if t.name in ("dut", "sim-modbus")]
        assert len(sim_threads) == 2
        assert [nice_of(t.native_id or 0) for t in sim_threads] == [own, own]
    finally:
        cage.stop()


def test_nothing_changes_on_simulated_time() -> None:
    own = nice_of(threading.get_native_id())
    with timebase.simulated(), instrument_priority() as raised:
        assert raised is False
        assert nice_of(threading.get_native_id()) == own
