"""The guardian: a small process that switches every output off if the rig process dies unsafe.

Nothing inside a SIGKILLed (or OOM-killed, or crashed interpreter) rig process can reach the
hardware, so ``rig run`` starts this guardian first. It holds the read end of a pipe whose write
end only the rig process has; the operating system closes that end when the process dies, however
it dies. A clean exit writes ``done`` first and the guardian leaves quietly; end of file without
``done`` means the rig died, and the guardian opens every Modbus output of the rig configuration
(coil supplies, polarity relays, load channels), calls ``safe()`` on each, marks the run
incomplete and records what it did in the run's store. It holds no port while the rig runs.

    python -m rig.engine.guardian RIG.toml RUN_FOLDER    (started by the runner, not by hand)
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import IO

from drivers.registry import output_kinds

OUTPUT_KINDS = output_kinds()
"""Kinds the guardian switches off: every registered supply, load and relay (drivers.registry)."""
DONE = b"done\n"


class Guardian:
    """The runner's side: start the guardian; ``release()`` on a clean exit."""

    def __init__(self, rig_config: Path, folder: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rig.engine.guardian", str(rig_config), str(folder)],
            stdin=subprocess.PIPE,
            start_new_session=True,  # a Ctrl-C for the rig must not reach the guardian
        )

    def release(self) -> None:
        """The rig has safed its outputs itself: tell the guardian to leave without acting."""
        assert self.proc.stdin is not None
        with contextlib.suppress(OSError):
            self.proc.stdin.write(DONE)
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def safe_outputs(rig_config: Path) -> tuple[list[str], list[str]]:
    """Switch off every supply, load and relay board of ``rig_config``: (devices, problems)."""
    from rig.config import load_rig_config
    from rig.engine.session import switch_off_every_output

    return switch_off_every_output(load_rig_config(rig_config))


def _record(folder: Path, t_died: float, done: list[str], problems: list[str]) -> None:
    """Mark the run incomplete and log what the guardian did (the run's own clock)."""
    path = folder / "run.sqlite"
    if not path.exists():
        return
    took_ms = 1000.0 * (time.monotonic() - t_died)
    message = f"guardian: the rig process died without going safe; switched off {', '.join(done) or 'nothing'} in {took_ms:.0f} ms"
    con = sqlite3.connect(path, timeout=10.0)
    try:
        rows = [(time.monotonic(), "error", message)]
        rows += [(time.monotonic(), "error", f"guardian could not safe {p}") for p in problems]
        con.executemany("INSERT INTO events VALUES (?, ?, ?)", rows)
        con.execute(
            "INSERT OR REPLACE INTO meta VALUES ('status', ?), ('reason', ?)",
            (
                json.dumps("incomplete"),
                json.dumps("the rig process was killed; the guardian switched the outputs off"),
            ),
        )
        con.commit()
    finally:
        con.close()
    from rig.store.seal import seal_run

    seal_run(folder)  # the run is closed now: its data never change again


def watch(pipe: IO[bytes], rig_config: Path, folder: Path) -> int:
    """Wait for the rig to finish; act if it died. Returns the exit status."""
    data = b""
    while chunk := pipe.read(64):
        data += chunk
    if DONE in data:
        return 0
    t_died = time.monotonic()
    done, problems = safe_outputs(rig_config)
    with contextlib.suppress(sqlite3.Error, OSError):
        _record(folder, t_died, done, problems)
    for p in problems:
        print(
            f"rig guardian: WARNING: could not switch off {p}; switch it off by hand",
            file=sys.stderr,
        )
    return 1 if problems else 0


def main(argv: list[str]) -> int:
    """Entry point of ``python -m rig.engine.guardian RIG.toml RUN_FOLDER``."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # only the pipe ends the guardian
    import rig.engine.session  # noqa: F401 - imported now, so acting after a death takes no import time

    return watch(sys.stdin.buffer, Path(argv[0]), Path(argv[1]))


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
