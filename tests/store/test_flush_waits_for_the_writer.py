"""A flush (a step about to read the run's store) includes the rows the writer thread has taken
off the queue and not yet committed: a step never reads a store missing them."""

from __future__ import annotations

import threading
from pathlib import Path

from rig.store import RunReader, new_run


def test_a_flush_waits_for_rows_the_writer_thread_holds(tmp_path: Path) -> None:
    writer = new_run(tmp_path / "runs", "race")
    held, go = threading.Event(), threading.Event()
    begin = writer._begin_if_ours

    def slow_begin() -> bool:  # the writer thread descheduled between taking rows and writing them
        if threading.current_thread() is writer._thread and not go.is_set():
            held.set()
            go.wait(10.0)
        return begin()

    writer._begin_if_ours = slow_begin  # type: ignore[method-assign]
    for i in range(10):
        writer.add_sample(float(i), "dut", (1.0, 2.0, 3.0))
    assert held.wait(10.0), "the writer thread did not take the rows"
    threading.Timer(0.2, go.set).start()
    writer.flush()
    reader = RunReader(writer.folder)
    try:
        assert reader.count("samples") == 10
    finally:
        reader.close()
        writer.close("complete", "done")
