"""A writer whose run another process closed writes nothing more (issue 51, ADR 0036): no row, no
metadata, no status, no lease, no new seal; it says so in ``closed_by_other``."""

from __future__ import annotations

import json
import sqlite3
import time
from pathlib import Path

from rig.store import new_run
from rig.store.seal import seal_run, verify_run


def close_as_a_reader(folder: Path) -> None:
    """What a reader that found the lease expired does: mark incomplete, then seal."""
    con = sqlite3.connect(folder / "run.sqlite", timeout=10)
    try:
        con.execute("INSERT OR REPLACE INTO meta VALUES ('status', ?), ('reason', ?)",
                    (json.dumps("incomplete"), json.dumps("lease expired")))  # fmt: skip
        con.commit()
    finally:
        con.close()
    seal_run(folder)


def meta_of(folder: Path) -> dict[str, object]:
    con = sqlite3.connect(f"file:{folder / 'run.sqlite'}?mode=ro", uri=True)
    try:
        return {k: json.loads(v) for k, v in con.execute("SELECT key, value FROM meta")}
    finally:
        con.close()


def test_a_writer_writes_nothing_after_another_process_closed_its_run(tmp_path: Path) -> None:
    w = new_run(tmp_path, "closed")
    w.add_sample(1.0, "dut", (1.0, 2.0, 3.0))
    w.flush()
    assert w.rows_written == 1 and w.closed_by_other is None
    close_as_a_reader(w.folder)
    meta, seal = meta_of(w.folder), (w.folder / "seal.json").read_bytes()
    for i in range(5):
        w.add_sample(2.0 + i, "dut", (0.0, 0.0, 0.0))
    w.add_event(2.0, "info", "after the seal")
    w.flush()
    assert w.closed_by_other == "incomplete (lease expired)"
    assert w.rows_written == 1 and w.rows_dropped == 6
    w.set_meta(status="complete", verdict="PASS")
    w.set_result("calibration", {"scale": 1.0})
    w.set_step(0, "s", "hold", 0.0, 1.0)
    time.sleep(0.3)  # a lease renewal or a batch of the commit thread, had it written
    w.add_sample(9.0, "dut", (0.0, 0.0, 0.0))
    assert w.close("complete", "all steps done") == []
    assert w.rows_dropped == 7
    assert meta_of(w.folder) == meta
    assert (w.folder / "seal.json").read_bytes() == seal
    assert verify_run(w.folder).intact


def test_a_writer_of_a_running_run_still_writes_and_seals(tmp_path: Path) -> None:
    w = new_run(tmp_path, "open")
    w.add_sample(1.0, "dut", (1.0, 2.0, 3.0))
    w.set_meta(verdict="PASS")
    assert w.close("complete", "all steps done") == []
    assert w.closed_by_other is None and w.rows_dropped == 0
    assert meta_of(w.folder)["status"] == "complete"
    assert verify_run(w.folder).intact
