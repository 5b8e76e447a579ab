"""After a run's null hold: the calibrations to come predicted again on this DUT's noise when it
differs from its history (:mod:`rig.prediction.at_null`), beside the run (a second of computing
must not hold the cage), kept in the run's meta and said in its events."""

from __future__ import annotations

import contextlib
from typing import Any

import timebase
from rig.procedure.plan import rig_timing


def start_after_null(run: Any, null_name: str) -> None:
    """Start the prediction from ``run``'s (a Runner's) null hold ``null_name`` in a thread."""
    timebase.Thread(_after_null, args=(run, null_name), name="after-null", daemon=True).start()


def _after_null(run: Any, null_name: str) -> None:
    from rig.prediction.at_null import prediction_after_null, summary_line

    try:  # advisory: whatever goes wrong (a run already closed too) loses only this record
        record = prediction_after_null(run.proc, run.cfg, rig_timing(run.cfg), run.runs_dir,
                                       dict(run.results), null_name, run.folder.name)  # fmt: skip
        if record is not None:
            run.set_meta(prediction_after_null=record)
            # a unit unlike its history is worth the report's log (a warning: it says the
            # consequence), one that agrees only the events
            run.event("warning" if record["changed"] else "info", summary_line(record))
    except Exception as exc:
        with contextlib.suppress(Exception):
            run.event("info", f"no prediction after '{null_name}': {type(exc).__name__}: {exc}")
