"""The operator's channel to a run: yes/no questions answered on the terminal or the web page
(whichever first), and the signals that pause (SIGUSR1) or end (SIGTERM, SIGHUP) it.

A question is waited on in the run's time (:mod:`timebase`): in simulated time the simulated rig
runs on meanwhile, as a real one would. The terminal's reader thread is outside any simulated
clock: it only puts lines in a queue of the clock the question was asked on."""

from __future__ import annotations

import queue
import signal
import sys
import threading
from collections.abc import Callable
from types import FrameType
from typing import Any

import timebase
from rig.engine.page_feed import LivePublisher
from rig.engine.run_tracker import RunTracker
from rig.engine.session import RigSession
from rig.errors import RigError, RunAborted

Confirm = Callable[[str], bool]


class OperatorChannel:
    """Asks one run's operator; ``confirm`` (``--yes``, tests) answers instead when given."""

    def __init__(self, confirm: Confirm | None, page_url: str | None,
                 event: Callable[[str, str], None]) -> None:  # fmt: skip
        self.confirm = confirm
        self.page_url = page_url  # the web page serving this run (rig run --serve), if any
        self.event = event

    def ask(self, rig: RigSession, publisher: LivePublisher, text: str) -> bool:
        """A yes/no question, answered by ``confirm``, or on the web page or the terminal,
        whichever answers first. Without a terminal the page alone can answer."""
        with rig.waiting_for_operator():  # as long as the operator takes: not a hang
            if self.confirm is not None:
                return self.confirm(text)
            prompt = publisher.open_prompt(text)
            self.event("operator", f"asked: {text}")
            try:
                return self._first_answer(rig, publisher, prompt, text)
            finally:
                publisher.close_prompt()

    def _first_answer(self, rig: RigSession, publisher: LivePublisher, prompt: int,
                      text: str) -> bool:  # fmt: skip
        terminal = _terminal_answers() if sys.stdin.isatty() else None
        if terminal is not None:
            terminal.ask(f"\n{text} [y/N] ")
        elif self.page_url is None:
            raise RigError(f"the procedure asks the operator: {text!r}; run in a terminal,"
                           " answer it on the page ('rig run --serve'), or pass --yes")  # fmt: skip
        while True:
            rig.check()  # an abort (page, signal) ends the question too
            page = publisher.wait_answer(prompt, 0.1)
            if page is not None:
                if terminal is not None:
                    print("(answered on the web page)", file=sys.stderr)
                return page
            if terminal is not None:
                line = terminal.answer()
                if line is not None:
                    return line.strip().lower() in ("y", "yes")


def install_signals(tracker: RunTracker) -> dict[int, Any]:
    """SIGTERM and SIGHUP (the terminal went away) end the run, SIGUSR1 pauses or resumes it;
    returns the handlers they replace (none off the main thread, where Python cannot set them)."""
    if threading.current_thread() is not threading.main_thread():
        return {}

    def on_term(signum: int, frame: FrameType | None) -> None:
        raise RunAborted(f"stopped by {signal.Signals(signum).name}")

    def on_usr1(signum: int, frame: FrameType | None) -> None:
        tracker.toggle_pause()

    return {
        signal.SIGTERM: signal.signal(signal.SIGTERM, on_term),
        signal.SIGHUP: signal.signal(signal.SIGHUP, on_term),
        signal.SIGUSR1: signal.signal(signal.SIGUSR1, on_usr1),
    }


def restore_signals(old: dict[int, Any]) -> None:
    """Put back the handlers :func:`install_signals` replaced."""
    for s, h in old.items():
        signal.signal(s, h)


class _TerminalAnswers:
    """Lines typed on the terminal, read by one thread for the whole process: a question answered
    on the page leaves no reader behind to steal the next answer (stale lines are dropped)."""

    def __init__(self) -> None:
        self.lines: queue.Queue[str] = timebase.Queue()
        self._thread = threading.Thread(target=self._read, name="terminal-answers", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        for line in sys.stdin:
            self.lines.put(line)

    def ask(self, question: str) -> None:
        """Drop what was typed before and show ``question`` (its answers go to a new queue, of
        the clock the question is asked on)."""
        self.lines = timebase.Queue()
        print(question, end="", file=sys.stderr, flush=True)

    def answer(self) -> str | None:
        """A line typed since :meth:`ask`, or None."""
        try:
            return self.lines.get_nowait()
        except queue.Empty:
            return None


_TERMINAL: list[_TerminalAnswers] = []


def _terminal_answers() -> _TerminalAnswers:
    if not _TERMINAL:
        _TERMINAL.append(_TerminalAnswers())
    return _TERMINAL[0]
