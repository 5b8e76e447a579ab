"""The simulated clock (ADR 0038): time jumps to the earliest deadline, one participant runs at a
time, the same inputs give the same interleaving, waits on events, locks, queues and pipes."""

from __future__ import annotations

import hashlib
import threading
import time

import pytest
import serial

import timebase
from timebase.sim_clock import NotOnTheClockError
from timebase.wires import wires


def test_sleep_jumps_instead_of_waiting() -> None:
    t0 = time.monotonic()
    with timebase.simulated() as clock:
        timebase.sleep(3600.0)
        assert timebase.monotonic() == 3600.0
        assert clock.wall_time() - time.time() == pytest.approx(3600.0, abs=5.0)
    assert time.monotonic() - t0 < 1.0
    assert not timebase.is_simulated()


def test_threads_take_turns_in_deadline_order_and_the_same_every_time() -> None:
    def once() -> list[tuple[float, str]]:
        log: list[tuple[float, str]] = []
        with timebase.simulated():

            def ticker(name: str, period: float) -> None:
                for _ in range(20):
                    timebase.sleep(period)
                    log.append((timebase.monotonic(), name))

            threads = [timebase.Thread(ticker, name=n, args=(n, p))
                       for n, p in (("a", 0.3), ("b", 0.2), ("c", 0.1))]  # fmt: skip
            for t in threads:
                t.start()
            for t in threads:
                t.join()
        return log

    first = once()
    assert [t for t, _ in first] == sorted(t for t, _ in first)
    assert first[:3] == [(0.1, "c"), (0.2, "b"), (pytest.approx(0.2), "c")]
    assert once() == first
    assert first[-1][0] == pytest.approx(6.0)


def test_events_queues_and_conditions_wake_on_simulated_time() -> None:
    with timebase.simulated():
        ev = timebase.Event()
        q = timebase.Queue()
        cond = timebase.Condition()
        seen: list[tuple[str, float]] = []

        def producer() -> None:
            timebase.sleep(1.0)
            ev.set()
            timebase.sleep(1.0)
            q.put("item")
            timebase.sleep(1.0)
            with cond:
                cond.notify_all()

        t = timebase.Thread(producer, name="producer")
        t.start()
        assert not ev.wait(0.5)
        assert timebase.monotonic() == 0.5
        assert ev.wait(10.0)
        seen.append(("event", timebase.monotonic()))
        seen.append((q.get(timeout=5.0), timebase.monotonic()))
        with cond:
            assert cond.wait(5.0)
        seen.append(("cond", timebase.monotonic()))
        t.join()
        assert seen == [("event", 1.0), ("item", 2.0), ("cond", 3.0)]
        with pytest.raises(__import__("queue").Empty):
            q.get(timeout=0.25)
        assert timebase.monotonic() == 3.25


def test_a_lock_held_across_a_wait_lets_the_others_run() -> None:
    with timebase.simulated():
        lock = timebase.RLock()
        order: list[str] = []

        def holder() -> None:
            with lock:
                order.append("holder in")
                timebase.sleep(0.5)  # a Modbus exchange, say
                order.append("holder out")

        def other() -> None:
            timebase.sleep(0.1)
            with lock:
                order.append(f"other at {timebase.monotonic():g}")

        ts = [timebase.Thread(holder, name="h"), timebase.Thread(other, name="o")]
        for t in ts:
            t.start()
        for t in ts:
            t.join()
        assert order == ["holder in", "holder out", "other at 0.5"]


def test_a_thread_outside_the_clock_may_wake_a_participant_but_not_wait() -> None:
    with timebase.simulated():
        ev = timebase.Event()
        threading.Thread(target=lambda: (time.sleep(0.05), ev.set()), daemon=True).start()
        assert ev.wait()  # the clock idles until the outside thread sets it
        outside: list[BaseException] = []

        def waits() -> None:
            try:
                timebase.sleep(1.0)
            except NotOnTheClockError as exc:
                outside.append(exc)

        th = threading.Thread(target=waits)
        th.start()
        th.join()
        assert outside and "timebase.Thread" in str(outside[0])


def test_a_serial_line_delivers_at_its_baud_rate_through_pyserial() -> None:
    with timebase.simulated():
        line = wires().serve_serial("dut", baud=19200)
        port = serial.serial_for_url(line.url, baudrate=9600, timeout=0.5)
        assert line.client.client_baud == 9600
        port.baudrate = 19200
        assert line.client.client_baud == 19200

        def device() -> None:
            request = line.device.read(4, None)
            assert request == b"*99\r"
            line.device.write(b"x" * 96)  # 96 bytes at 19200 Bd: 50 ms on the line

        t = timebase.Thread(device, name="device")
        t.start()
        port.write(b"*99\r")
        t0 = timebase.monotonic()
        assert port.read(96) == b"x" * 96
        assert timebase.monotonic() - t0 == pytest.approx(4 * 10 / 19200 + 0.05)
        port.timeout = 0.25
        assert port.read(1) == b""  # a timeout of simulated time
        assert timebase.monotonic() - t0 == pytest.approx(4 * 10 / 19200 + 0.3)
        t.join()
        with pytest.raises(serial.SerialException, match="no simulated line"):
            serial.serial_for_url("simpipe://nothing")


def test_loopback_connections_and_refusal() -> None:
    with timebase.simulated():
        net = wires()
        served: list[bytes] = []

        def accept(end: timebase.wires.PipeEnd) -> None:  # type: ignore[name-defined]
            def serve() -> None:
                while end.wait_readable(None) and not end.peer_closed:
                    data = end.read_available()
                    served.append(data)
                    end.write(data.upper())
                end.close()

            timebase.Thread(serve, name="server", daemon=True).start()

        port = net.listen("127.0.0.1", 0, accept)
        client = net.connect("localhost", port)
        client.write(b"abc")
        assert client.read(3, 1.0) == b"ABC"
        client.close()
        timebase.sleep(0.01)
        assert served == [b"abc"]
        with pytest.raises(ConnectionRefusedError):
            net.connect("127.0.0.1", port + 1)


def test_the_same_work_gives_the_same_record_under_any_load() -> None:
    """Four threads exchange bytes and random draws; the record's hash is fixed."""

    def record() -> str:
        import random

        h = hashlib.sha256()
        with timebase.simulated():
            line = wires().serve_serial("s", baud=115200)
            port = serial.serial_for_url(line.url, timeout=0.1)
            rng = random.Random(1)

            def talker() -> None:
                for k in range(200):
                    line.device.write(f"{k} {rng.random():.6f}\n".encode())
                    timebase.sleep(0.01)

            def sampler() -> None:
                for _ in range(50):
                    timebase.sleep(0.037)
                    h.update(f"{timebase.monotonic():.9f} {rng.random():.6f}".encode())

            ts = [timebase.Thread(talker, name="t"), timebase.Thread(sampler, name="s")]
            for t in ts:
                t.start()
            while (chunk := port.read(64)) or any(t.is_alive() for t in ts):
                h.update(f"{timebase.monotonic():.9f}".encode() + chunk)
            for t in ts:
                t.join()
        return h.hexdigest()

    first = record()
    hogs = [threading.Thread(target=lambda: sum(i * i for i in range(3_000_000)), daemon=True)
            for _ in range(2)]  # fmt: skip
    for hog in hogs:
        hog.start()
    assert record() == first


def test_a_writer_sees_what_its_reader_has_not_taken_and_a_line_changes_speed() -> None:
    with timebase.simulated():
        line = wires().serve_serial("backlog", baud=9600)
        line.device.write(b"abcd")
        assert line.device.out_waiting == 4  # on the line: 4 bytes at 9600 Bd take 4.17 ms
        timebase.sleep(0.01)
        assert line.client.read_available(3) == b"abc"
        assert line.device.out_waiting == 1
        line.client.discard_input()
        assert line.device.out_waiting == 0
        line.set_baud(19200)
        t0 = timebase.monotonic()
        line.device.write(b"x" * 96)
        assert line.client.read(96, 1.0) == b"x" * 96
        assert timebase.monotonic() - t0 == pytest.approx(96 * 10 / 19200)
        assert line.device.out_waiting == 0


def test_a_participant_blocked_outside_the_clock_is_reported_with_what_everyone_waits_for() -> None:
    import io

    from timebase.stall_watch import StallWatch

    outside = threading.Lock()
    outside.acquire()  # held by this test's helper thread below, as a database's lock would be
    out = io.StringIO()
    with timebase.simulated(stall_report_s=None) as clock:
        watch = StallWatch(clock, stall_s=0.3, out=out)
        sleeper = timebase.Thread(lambda: timebase.sleep(5.0), name="sleeper")
        sleeper.start()
        timebase.sleep(0.0)  # the sleeper runs and waits for t = 5 s
        threading.Timer(1.5, outside.release).start()  # a wall-clock thread, no participant
        t0 = time.monotonic()
        with outside:  # the participant holding the turn blocks on a plain lock
            pass
        sleeper.join()
        watch.stop()
    report = out.getvalue()
    assert watch.reports == 1, report
    assert time.monotonic() - t0 >= 1.4
    assert "simulated clock stalled" in report
    assert "MainThread: has the turn" in report
    assert "sleeper: waiting until t = 5.000000 s" in report
    assert "test_simulated_clock.py" in report  # the stacks show where it blocked


def test_a_busy_host_wakes_its_threads_late_the_instruments_on_time_and_the_same_every_time() -> (
    None
):
    """timebase.busy_host: a host thread's every wake is late by its own seeded delays; a thread
    of the simulator (sim.*) keeps simulated time exactly."""
    from sim import transports  # any sim module: a target defined there is an instrument's

    def once(seed: int) -> tuple[list[float], list[float]]:
        host_t: list[float] = []
        inst_t: list[float] = []

        def instrument() -> None:
            for _ in range(20):
                timebase.sleep(0.1)
                inst_t.append(timebase.monotonic())

        instrument.__module__ = transports.__name__
        with timebase.simulated(busy=timebase.BusyHost(0.05, seed=seed)):
            thread = timebase.Thread(instrument, name="instrument")
            thread.start()
            for _ in range(20):
                timebase.sleep(0.1)
                host_t.append(timebase.monotonic())
            thread.join()
        return host_t, inst_t

    host, inst = once(1)
    assert inst == pytest.approx([0.1 * (k + 1) for k in range(20)])
    late = [b - a - 0.1 for a, b in zip([0.0, *host], host, strict=False)]
    assert min(late) >= 0.0 and 0.02 < sum(late) / len(late) < 0.1  # mean 0.05 s
    assert once(1) == (host, inst)  # deterministic
    assert once(2)[0] != host  # its own stream per seed


def test_a_clock_says_how_late_it_may_wake_unseen() -> None:
    """A stream's date uncertainty claims at least the clock's unseen wake-up lateness (ADR 0042
    amended): the wall clock's scheduler, 1 ms; none on simulated time, where a participant runs
    at the time it waited for (a 1 ms floor there made an idle frequency response's phase sigmas
    30 times its errors)."""
    from rig.engine.stream_clock import StreamClock

    assert timebase.wake_jitter_s() == 0.001
    with timebase.simulated():
        assert timebase.wake_jitter_s() == 0.0
    clock = StreamClock(0.05, timebase.wake_jitter_s())
    exact = [clock.dated(100.0 + 0.05 * k + 0.003)[0] for k in range(400)]
    assert exact[-1][1] < 1.1e-3  # arrivals within microseconds: the floor is what is claimed
    on_time = StreamClock(0.05, 0.0)
    tight = [on_time.dated(100.0 + 0.05 * k + 0.003)[0] for k in range(400)]
    assert tight[-1][1] < 1e-4 and abs(tight[-1][0] - (100.0 + 0.05 * 399 + 0.003)) < 1e-9
