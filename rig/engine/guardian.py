"""The guardian: a small process that switches every output off if the rig process dies or hangs.

Nothing inside a SIGKILLed (or OOM-killed, or crashed interpreter) rig process can reach the
hardware, and a process that is stopped, deadlocked or stuck in a long computation does not
notice anything, so every command that drives outputs (``rig run``, ``rig demo``, ``rig cage
...``, all through :class:`rig.engine.session.RigSession`) starts this guardian first. It holds
the read end of a pipe whose write end only the rig process has:

* the rig writes a heartbeat byte every :data:`HEARTBEAT_PERIOD_S` while its main thread makes
  progress (or waits for the operator);
* a clean exit writes ``done``: the guardian leaves quietly;
* end of file without ``done`` means the rig died;
* no heartbeat for :data:`HEARTBEAT_TIMEOUT_S` means it hung: the guardian kills it (SIGKILL, so a
  stopped process that is resumed later cannot drive the outputs again).

A run closed by another process while the rig was stopped is the third finding (see
:mod:`rig.engine.guardian_findings`, ADR 0036).

Either way it then opens every Modbus output of the rig configuration (coil supplies, load
channels, then the polarity relays once the coils are off), calls ``safe()`` on each, and, for a
run, marks the run incomplete and records what it did in the run's store. It inherits the rig's
interlock (rig.engine.interlock), so no other command can take the rig before it has finished.
It holds no port while the rig runs.

The configuration it acts on is the one the rig parsed, frozen (rig.engine.frozen_config) and
sent as the first line on the pipe; the guardian parses it before it waits and answers ``ready``
on its stdout, and never reads the configuration file (an edit during the run cannot stop it).
A guardian that cannot parse it exits without ``ready``, and the session refuses to start.
Its stdout stays open, unused, for as long as it lives: the rig sees it end (end of file) the
moment the guardian dies, and ends the command through its safe path (RigSession).

    python -m rig.engine.guardian RUN_FOLDER|- RIG_PID   (started by the session)
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from drivers.registry import output_kinds
from rig.config import RigConfig
from rig.engine import guardian_findings as findings
from rig.engine.cpu_priority import raise_own_priority
from rig.engine.cpu_wait import CpuWaitLog
from rig.engine.frozen_config import FrozenConfigError, freeze, thaw
from rig.engine.killed_rig import kill_rig
from rig.errors import RigError

OUTPUT_KINDS = output_kinds()
"""Kinds the guardian switches off: every registered supply, load and relay (drivers.registry)."""
DONE = b"done\n"
BEAT = b"."
HEARTBEAT_PERIOD_S = 0.2
"""How often the rig process tells the guardian it is alive."""
HEARTBEAT_TIMEOUT_S = 3.0
"""No heartbeat for this long: the rig process is hung (stopped, deadlocked, or stuck with the
interpreter held). 15 heartbeat periods: far beyond the scheduling stalls of a busy computer
(0.6 s seen on 2 cores with 4 CPU hogs), short beside a coil's thermal time constant."""
OWN_STALL_S = 0.5
"""The guardian's own wait took this much longer than asked: the guardian itself was descheduled,
so the silence it saw is not the rig's; the rig gets a fresh timeout."""


CLOSED_GRACE_S = 10.0
"""After switching the outputs off because another process closed the run, how long the guardian
waits for the rig to end through its own safe path (which takes ~1 s) before it kills it (s)."""


class ClosedByOther(str):
    """What :func:`wait_for_rig` returns when the run was closed by another process."""


START_TIMEOUT_S = 30.0
"""Longest wait for the guardian to say it is ready (its start-up takes ~0.3 s on an idle computer,
seconds on a busy one); then the session refuses to start rather than run unguarded."""
READY = b"ready\n"


class GuardianError(RigError):
    """The guardian could not start: the command is refused before any output is on."""


class Guardian:
    """The rig's side: start the guardian with the frozen configuration, ``beat()`` while alive,
    ``release()`` on a clean exit; :meth:`gone` tells when it died.

    ``cfg`` is the configuration the rig parsed (the guardian acts on exactly its devices);
    ``folder`` is the run folder to record into (None: a command without a run); ``lock_fds``
    are the interlock's descriptors, inherited so that the rig stays locked until the guardian
    is done. Raises GuardianError if the guardian does not say ``ready`` within
    :data:`START_TIMEOUT_S`.
    """

    def __init__(self, cfg: RigConfig, folder: Path | None, lock_fds: tuple[int, ...] = ()) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rig.engine.guardian",
             str(folder) if folder is not None else "-", str(os.getpid())],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            pass_fds=lock_fds,
            start_new_session=True,  # a Ctrl-C for the rig must not reach the guardian
        )  # fmt: skip
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self._fd = self.proc.stdin.fileno()
        self._status_fd = self.proc.stdout.fileno()
        self._gone = False
        self.stopped = False
        """Found stopped by :meth:`gone`."""
        try:
            with contextlib.suppress(OSError):  # one that ended at once: _await_ready says how
                _write_all(self._fd, (freeze(cfg) + "\n").encode())
            self._await_ready()
        except BaseException:
            self.proc.kill()
            self.proc.wait()
            self._close_pipes()
            raise

    def _await_ready(self) -> None:
        said = b""
        deadline = time.monotonic() + START_TIMEOUT_S
        while READY not in said:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._status_fd], [], [], left)[0]:
                raise GuardianError(
                    f"the guardian process did not start within {START_TIMEOUT_S:g} s, so the"
                    " outputs would be unguarded: nothing was switched on; try again on a less"
                    " busy computer"
                )
            chunk = os.read(self._status_fd, 64)
            if not chunk:
                code = self.proc.wait()
                raise GuardianError(
                    f"the guardian process could not start ({_how_it_ended(code)}), so the"
                    " outputs would be unguarded: nothing was switched on; see its line above"
                )
            said += chunk

    def beat(self) -> bool:
        """One heartbeat; False if the guardian is gone (the outputs are then unguarded)."""
        try:
            os.write(self._fd, BEAT)
            return True
        except OSError:
            return False

    def gone(self, wait_s: float = 0.0) -> str | None:
        """Wait up to ``wait_s`` for the guardian to end; what became of it if it can no longer
        act (``died (killed by SIGKILL)``, ``is stopped (...)``), else None. Its stdout reaches end
        of file the moment it dies, so this returns at once then."""
        if not self._gone:
            if not select.select([self._status_fd], [], [], max(0.0, wait_s))[0]:
                return "is stopped (SIGSTOP, or a debugger holds it)" if self._stopped() else None
            if os.read(self._status_fd, 64):  # it writes nothing after ready: not an end
                return None
            self._gone = True
        try:
            code = self.proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            return "closed its end of the pipe"
        return f"died ({_how_it_ended(code)})"

    def _stopped(self) -> bool:
        """True while the guardian process is stopped (state T or t in /proc): it would not act
        if the rig died now (a busy computer's waiting for a CPU is state R, not this)."""
        self.stopped = findings.process_stopped(self.proc.pid)
        return self.stopped

    def release(self) -> None:
        """The rig has safed its outputs itself: tell the guardian to leave without acting (a
        stopped one is killed: it holds the interlock until it ends)."""
        with contextlib.suppress(OSError):
            os.write(self._fd, DONE)
        self._close_pipes()
        if self.stopped:
            self.proc.kill()
        try:
            self.proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def _close_pipes(self) -> None:
        for pipe in (self.proc.stdin, self.proc.stdout):
            if pipe is not None:
                with contextlib.suppress(OSError):
                    pipe.close()


def _write_all(fd: int, data: bytes) -> None:
    """Write all of ``data`` to ``fd`` (a pipe takes 64 KiB at a time)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def _how_it_ended(code: int) -> str:
    """``killed by SIGKILL`` or ``exit status 2``, from a Popen return code."""
    if code < 0:
        with contextlib.suppress(ValueError):
            return f"killed by {signal.Signals(-code).name}"
        return f"killed by signal {-code}"
    return f"exit status {code}"


def safe_outputs(cfg: RigConfig) -> tuple[list[str], list[str], str]:
    """Switch off every supply, load and relay board of ``cfg``: (devices, problems, the slowest
    output when it was slow)."""
    from rig.engine.switch_off import switch_off_every_output  # light to import the guardian

    return switch_off_every_output(cfg)


def wait_for_rig(
    fd: int,
    pid: int,
    timeout_s: float = HEARTBEAT_TIMEOUT_S,
    waits: CpuWaitLog | None = None,
    closed: Callable[[], str | None] | None = None,
    kill_at: float | None = None,
) -> str | None:
    """Read heartbeats until the rig says ``done`` (None) or dies or hangs (why, one phrase).
    A hung rig is killed first, so that it cannot drive the outputs again once resumed.

    Time the guardian itself was not running (its 0.1 s wait took more than OWN_STALL_S longer)
    is not the rig's silence: that much is added to the rig's time, and no more. ``waits``, if
    given, is noted every round (the guardian's own waits for a CPU, for its account).
    ``closed``, if given, is asked every round whether another process closed the run (the
    status it stored): then a :class:`ClosedByOther` is returned at once, the rig left running
    (it ends through its own safe path). A rig still there at ``kill_at`` (monotonic s) is
    killed as a hung one is."""
    tail = b""
    last_beat = time.monotonic()
    own_stall_s = 0.0  # guardian stalls discounted since the last beat
    while True:
        before = time.monotonic()
        if waits is not None:
            waits.note(before)
        ready, _, _ = select.select([fd], [], [], 0.1)
        now = time.monotonic()
        late = now - before - 0.1
        if late > OWN_STALL_S:
            own_stall_s += late  # we were not running: the rig's silence was not measured
        stored = closed() if closed is not None else None
        if stored is not None:
            return ClosedByOther(
                f"the run was closed by another process while the rig was stopped (stored:"
                f" {stored})"
            )
        if kill_at is not None and now >= kill_at:
            kill_rig(fd, pid)
            return (
                f"the rig process did not end within {CLOSED_GRACE_S:g} s of its run being closed"
                " by another process and was killed"
            )
        if ready:
            chunk = os.read(fd, 4096)
            if not chunk:
                return None if DONE in tail else "the rig process died without going safe"
            tail = (tail + chunk)[-len(DONE) :]
            last_beat, own_stall_s = now, 0.0
            continue
        if now - last_beat - own_stall_s > timeout_s:
            kill_rig(fd, pid)
            ours = (
                f", {own_stall_s:.1f} s more while the guardian waited for a CPU"
                if own_stall_s
                else ""
            )
            return (
                f"the rig process stopped answering (no heartbeat for {now - last_beat - own_stall_s:.1f} s{ours}:"
                " hung, stopped or deadlocked) and was killed"
            )


def watch(fd: int, cfg: RigConfig, folder: Path | None, pid: int) -> int:
    """Wait for the rig to finish; act if it died or hung, or if another process closed its run,
    on ``cfg`` (the frozen copy). Returns the exit status."""
    waits = CpuWaitLog(keep=64)
    closed = None if folder is None else (lambda: findings.run_closed_by_other(folder))
    why = wait_for_rig(fd, pid, waits=waits, closed=closed)
    if why is None:
        return 0
    if isinstance(why, ClosedByOther):
        return _closed_by_other(fd, cfg, pid, why, waits)
    t_found = time.monotonic()
    done, problems, slowest = safe_outputs(cfg)
    cpu = findings.busy_note(waits, t_found) + slowest
    if folder is not None:
        with contextlib.suppress(sqlite3.Error, OSError):
            findings.record_in_run(folder, t_found, why, done, problems, cpu)
    return _tell(why, t_found, done, problems, cpu)


def _tell(why: str, t_found: float, done: list[str], problems: list[str], cpu: str = "",
          t_done: float | None = None) -> int:  # fmt: skip
    """The guardian's lines on what it did (stderr; ``t_done``: when the switch-off ended,
    monotonic s, now when None); its exit status (1: an output not off)."""
    took_ms = 1000.0 * ((time.monotonic() if t_done is None else t_done) - t_found)
    print(f"rig guardian: {why}; switched off {', '.join(done) or 'nothing'} in {took_ms:.0f} ms"
          f"{cpu}", file=sys.stderr)  # fmt: skip
    for p in problems:
        print(
            f"rig guardian: WARNING: could not switch off {p}; switch it off by hand",
            file=sys.stderr,
        )
    return 1 if problems else 0


def _closed_by_other(fd: int, cfg: RigConfig, pid: int, why: str, waits: CpuWaitLog) -> int:
    """Another process closed the run while the rig was stopped (ADR 0036). A rig still stopped
    cannot take its own safe path and holds its ports: it is killed, then every output switched
    off. A running rig finds the same and ends through its safe path: every output the guardian
    can reach is switched off at once (one the rig holds open, a serial port, is left to it), the
    rig is given :data:`CLOSED_GRACE_S` to end (else killed), and whatever was not reached is
    switched off once it has. The closed run is never written to."""
    t_found = time.monotonic()
    if findings.stays_stopped(pid):
        ended = kill_rig(fd, pid)
        done, problems, slowest = safe_outputs(cfg)
        t_done = time.monotonic()
        return _tell(f"{why}; the rig process was still stopped and was killed", t_found, done,
                     problems, findings.busy_note(waits, t_found) + ended() + slowest, t_done)  # fmt: skip
    done, held, slowest = safe_outputs(cfg)
    cpu = findings.busy_note(waits, t_found) + slowest
    left = f"; {len(held)} not reached yet (held by the rig, which is going safe)" if held else ""
    _tell(why, t_found, done, [], cpu + left)
    later = wait_for_rig(fd, pid, waits=waits, kill_at=time.monotonic() + CLOSED_GRACE_S)
    if later is None and not held:
        return 0
    t_again = time.monotonic()
    done, problems, slowest = safe_outputs(cfg)
    return _tell(later or "the rig process went safe and ended", t_again, done, problems, slowest)


def read_config_line(fd: int) -> RigConfig:
    """The frozen configuration the rig sends first on the pipe (one line); FrozenConfigError if
    it is not one, EOFError if the pipe ends before the line does."""
    line = b""
    while not line.endswith(b"\n"):
        chunk = os.read(fd, 65536)
        if not chunk:
            raise EOFError("the rig process ended before it sent its configuration")
        line += chunk
        if b"\n" in line[:-1]:  # the rig waits for ready before it beats: nothing may follow
            raise FrozenConfigError("more than one line before ready")
    return thaw(line.decode("utf-8", errors="replace"))


def main(argv: list[str]) -> int:
    """Entry point of ``python -m rig.engine.guardian RUN_FOLDER|- RIG_PID``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # only the pipe ends the guardian
    raise_own_priority()  # before any thread starts: they inherit it
    import rig.engine.switch_off  # noqa: F401 - imported now, so acting after a death takes no import time

    try:
        cfg = read_config_line(sys.stdin.fileno())
    except (FrozenConfigError, EOFError) as exc:
        print(f"rig guardian: cannot read the rig configuration the rig sent ({exc}); the rig"
              " refuses to start unguarded", file=sys.stderr)  # fmt: skip
        return 2
    os.write(sys.stdout.fileno(), READY)
    # the pipe stays open, unused, until this process ends (its end tells the rig it died); any
    # later print to stdout goes nowhere, so a rig that died first cannot break the guardian
    alive = os.dup(sys.stdout.fileno())  # noqa: F841 - held, never written
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, sys.stdout.fileno())
    os.close(null)
    folder = None if argv[0] == "-" else Path(argv[0])
    return watch(sys.stdin.fileno(), cfg, folder, int(argv[1]))


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
