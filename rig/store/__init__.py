"""The run store: one folder per run with a crash-safe SQLite database (WAL, batched commits)."""

from rig.store.run_store import RunReader, RunWriter, list_runs, new_run

__all__ = ["RunReader", "RunWriter", "list_runs", "new_run"]
