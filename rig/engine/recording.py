"""The run's record: its folder opened with what it runs and on what, closed with its status and the
figures of how it ran, then the report and the lab index (each best effort: the folder is the
record)."""

from __future__ import annotations

import json
import shutil
import socket
import sys
import time
from array import array
from pathlib import Path

import numpy as np

from rig import __version__
from rig.config import RigConfig
from rig.engine.sampling import SensorSampler
from rig.engine.switch_off import OutputState
from rig.procedure.language import Procedure
from rig.store import safe_files
from rig.store.run_states import RunStatus
from rig.store.run_store import RunWriter, new_run, now_iso
from rig.store.seal import SEAL_FILE, record_written

LAB_TIMEOUT_S = 5.0
"""Longest wait for the lab index at run close (s); then the run is synced later."""


def open_record(runs_dir: Path, proc: Procedure, cfg: RigConfig) -> RunWriter:
    """A new run folder for ``proc`` on ``cfg``'s rig, with copies of both files."""
    params = proc.parameters
    w = new_run(
        runs_dir, params.get("dut_serial") or proc.path.stem,
        procedure=proc.title, procedure_file=proc.path.name, parameters=params,
        operator=params.get("operator", ""), dut_serial=params.get("dut_serial", ""),
        software_version=__version__, rig_config=str(cfg.path), host=socket.gethostname(),
        magnetometers=proc.magnetometers, loads=list(proc.loads),
    )  # fmt: skip
    (w.folder / "procedure.yaml").write_text(proc.text, encoding="utf-8")
    # the bytes only: a group-writable configuration must not make a group-writable run file
    # (the lab sync skips those, docs/lab.md)
    shutil.copyfile(cfg.path, w.folder / "rig.toml")
    return w


def close_record(w: RunWriter, status: RunStatus, reason: str,
                 samplers: dict[str, SensorSampler], lateness_s: array[float]) -> None:  # fmt: skip
    """Store how the run went (samples per sensor, command lateness) and close it as ``status``;
    a problem closing it is one warning line (the data committed before it are kept)."""
    for name, s in samplers.items():
        w.set_meta(**{f"samples_{name}": s.count, f"retried_{name}": s.retried})
    if lateness_s:
        lat = np.frombuffer(lateness_s, dtype=float)
        w.set_meta(command_lateness_p50_ms=float(1000 * np.percentile(lat, 50)),
                   command_lateness_p99_ms=float(1000 * np.percentile(lat, 99)),
                   command_lateness_max_ms=float(1000 * lat.max()),
                   commands_scheduled=int(lat.size))  # fmt: skip
    for problem in w.close(status, reason):
        print(f"rig: WARNING: {problem}; the data committed before it is kept", file=sys.stderr)


AFTER_CLOSE_FILE = "closed-by-other.json"
"""Written beside the seal by a recorder that found its run closed by another process (ADR 0036)."""
SEAL_WAIT_S = 5.0
"""How long such a recorder waits for the other process's seal before noting the fact (s)."""


def note_closed_by_other(w: RunWriter, line: str, intended: str, outputs: str) -> None:
    """Record, in :data:`AFTER_CLOSE_FILE` beside the other process's seal (which stays as it is,
    as does the data it sealed), that this recorder carried on after the run was closed: its one
    ``line``, the status it would have stored (``intended``), the rows it did not store and the
    outputs as read back. The file is entered in the run's manifest (``rig verify`` lists it as
    written by the rig). Best effort: a failure is one warning line."""
    deadline = time.monotonic() + SEAL_WAIT_S  # the other process seals right after it marks
    while not (w.folder / SEAL_FILE).exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    note = {
        "written_at": now_iso(),
        "line": line,
        "would_have_stored": intended,
        "rows_not_stored": w.rows_dropped,
        "outputs": outputs,
        "rows_stored_by_this_process": w.rows_written,
    }
    path = w.folder / AFTER_CLOSE_FILE
    try:
        safe_files.write_text(path, json.dumps(note, indent=2) + "\n")
        record_written(w.folder, [path], "the recorder found its run closed by another process")
    except (OSError, safe_files.UnsafeFileError) as exc:
        print(f"rig: WARNING: could not write {path} ({exc})", file=sys.stderr)


def write_report(folder: Path, quiet: bool) -> None:
    """The acceptance report of the closed run; a failure leaves the run as recorded."""
    from rig.report.acceptance import build_report

    if not quiet:
        print("rig: writing the report ...", file=sys.stderr)
    try:
        build_report(folder)
    except Exception as exc:  # the run and its data stand; the report can be rebuilt
        print(f"rig: WARNING: the report could not be written ({type(exc).__name__}: {exc});"
              f" rebuild it with 'rig report {folder}'", file=sys.stderr)  # fmt: skip


def sync_lab(url: str, folder: Path, quiet: bool) -> None:
    """Push the closed run to the lab index; best effort: a failure is one warning line and the
    run stays as recorded ('rig lab sync' pushes it later)."""
    from rig.lab.sync import sync_runs
    from rig.lab.url import masked

    try:
        report = sync_runs(url, [folder], timeout_s=LAB_TIMEOUT_S)
        if report.added and not quiet:
            print(f"rig: run added to the lab index {masked(url)}", file=sys.stderr)
        for why in report.refused + report.not_stored + report.skipped + report.unreadable:
            print(f"rig: WARNING: the lab index did not take this run: {why}", file=sys.stderr)
    except Exception as exc:  # never a failed run: the folder is the record
        print(f"rig: WARNING: the run was not added to the lab index ({masked(str(exc))});"
              " 'rig lab sync' adds it later", file=sys.stderr)  # fmt: skip


def outputs_note(read_back: dict[str, OutputState] | None, cfg_path: Path) -> str:
    """One line on every output as read back after the session's safe path ('' when no session
    was entered): ``outputs: read back off: coil_x 0.000 A, ..., polarity normal`` or
    ``outputs: STILL ON or not confirmed off: heater 2.000 A (output enabled), ...`` and
    the fix."""
    if read_back is None:
        return ""
    if not read_back:
        return "outputs: none in the configuration"
    left = [s for s in read_back.values() if not s.off]
    if left:
        return (f"outputs: STILL ON or not confirmed off: {', '.join(s.short() for s in left)};"
                f" switch them off with 'rig safe --rig {cfg_path}' or by hand")  # fmt: skip
    return f"outputs: read back off: {', '.join(s.short() for s in read_back.values())}"
