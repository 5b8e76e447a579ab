"""What the pages show of the runs directory: summaries, one run's details, its downloadable files.

Read only, except that opening a run whose process died marks it incomplete (as ``rig runs``
does). Every file served is looked up by name among a run folder's own files: no path from a
request is ever joined to the file system, and a file or run folder that is a symbolic link (or not
a regular file) is neither listed nor served (:mod:`rig.store.safe_files`). A run whose store cannot
be read is listed as ``damaged`` with the reason; it never hides the others.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rig.store import RunReader, safe_files
from rig.store.run_control import LIVE_FILE, read_live
from rig.verdict import check_verdict

DOWNLOADS = {
    "report.pdf": "application/pdf",
    "report.html": "text/html; charset=utf-8",
    "samples_aligned.csv": "text/csv; charset=utf-8",
    "result.json": "application/json",
    "procedure.yaml": "text/plain; charset=utf-8",
    "rig.toml": "text/plain; charset=utf-8",
    "run.sqlite": "application/vnd.sqlite3",
}
"""Files of a run folder a page may offer, by name, with their media types."""
DOWNLOAD_SUFFIXES = {".csv": "text/csv; charset=utf-8", ".h5": "application/x-hdf5",
                     ".png": "image/png", ".json": "application/json"}  # fmt: skip
"""Other files of a run folder (exports, plots) offered by their suffix."""


@dataclass(frozen=True)
class RunSummary:
    """One row of the run browser."""

    run_id: str
    started: str
    procedure: str
    dut_serial: str
    operator: str
    status: str
    verdict: str | None
    reason: str

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return self.__dict__.copy()


DAMAGED = "damaged"
"""The status shown for a run folder whose store cannot be read."""


def is_run_folder(folder: Path) -> bool:
    """``folder`` is a real folder (not a link) holding a regular ``run.sqlite`` (not a link)."""
    try:
        safe_files.check_folder(folder)
    except safe_files.UnsafeFileError:
        return False
    return safe_files.is_regular_file(folder / "run.sqlite")


def run_folder(runs_dir: Path, run_id: str) -> Path | None:
    """The folder of ``run_id`` if it is a run directly in ``runs_dir``, else None."""
    for folder in runs_dir.iterdir() if runs_dir.is_dir() else ():
        if folder.name == run_id and is_run_folder(folder):
            return folder
    return None


def damage(exc: BaseException) -> str:
    """One line saying why a run's store cannot be read."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return f"cannot read run.sqlite ({text}); check it with 'rig verify'"


def summarize_run(folder: Path) -> RunSummary:
    """The run browser's row for one run folder."""
    reader = RunReader(folder)
    try:
        meta = reader.meta()
        verdict = check_verdict(reader.results())  # malformed: listed damaged, with the reason
    finally:
        reader.close()
    overall = str(verdict.overall) if verdict is not None else None
    start = str(meta.get("start_time", ""))
    try:
        started = dt.datetime.fromisoformat(start).strftime("%Y-%m-%d %H:%M:%S UTC")
    except ValueError:
        started = start
    return RunSummary(folder.name, started, str(meta.get("procedure", "")),
                      str(meta.get("dut_serial", "") or ""), str(meta.get("operator", "") or ""),
                      str(meta.get("status", "incomplete")), overall,
                      str(meta.get("reason", "") or ""))  # fmt: skip


def summary_or_damaged(folder: Path) -> RunSummary:
    """:func:`summarize_run`, or a ``damaged`` row saying why the store cannot be read."""
    try:
        return summarize_run(folder)
    except Exception as exc:  # a damaged run must not hide the others
        return RunSummary(folder.name, "", "", "", "", DAMAGED, None, damage(exc))


def list_summaries(runs_dir: Path) -> list[RunSummary]:
    """Every run under ``runs_dir``, newest first (one whose store cannot be read as damaged)."""
    if not runs_dir.is_dir():
        return []
    return [summary_or_damaged(folder) for folder in sorted(runs_dir.iterdir(), reverse=True)
            if is_run_folder(folder)]  # fmt: skip


def run_details(folder: Path) -> dict[str, Any]:
    """A run's page: summary, metadata, steps, events, results, files and live state."""
    reader = RunReader(folder)
    try:
        meta = reader.meta()
        steps = reader.steps()
        events = reader.events()
        results = reader.results()
    finally:
        reader.close()
    t0 = float(meta.get("start_monotonic", 0.0) or 0.0)
    verdict = check_verdict(results)
    return {
        "summary": summarize_run(folder).to_dict(),
        "meta": {k: v for k, v in meta.items() if not isinstance(v, dict | list)},
        "steps": [
            {
                "index": i,
                "name": n,
                "kind": k,
                "start_s": round(a - t0, 2),
                "end_s": None if b is None else round(b - t0, 2),
            }
            for i, n, k, a, b in steps
        ],
        "events": [{"t": round(t - t0, 2), "level": lv, "message": m} for t, lv, m in events],
        "verdict": verdict.to_dict() if verdict is not None else None,
        "files": downloads(folder),
        "plots": [name for name in downloads(folder) if name.endswith(".png")],
        "live": read_live(folder),
    }


def downloads(folder: Path) -> list[str]:
    """Names of the files of ``folder`` a page may offer for download."""
    names = []
    for path in sorted(folder.iterdir()):
        if (
            safe_files.is_regular_file(path)
            and not path.name.startswith(".")
            and path.name != LIVE_FILE
            and (path.name in DOWNLOADS or path.suffix in DOWNLOAD_SUFFIXES)
        ):
            names.append(path.name)
    return names


EXPORTS = {
    "csv": ("samples.zip", "application/zip"),
    "hdf5": ("run.h5", "application/x-hdf5"),
    "json": ("result.json", "application/json"),
}
"""Exports made on request from a closed run's store: format -> (file name suffix, media type)."""


def export_file(folder: Path, fmt: str, out_dir: Path) -> tuple[Path, str, str]:
    """Write the ``fmt`` export of ``folder`` into ``out_dir``; returns (path, download name,
    media type). CSV is every CSV file of ``rig export`` in one zip; JSON is every step result."""
    import json
    import zipfile

    from rig.store.export import export_csv, export_hdf5

    suffix, media = EXPORTS[fmt]
    name = f"{folder.name}-{suffix}"
    path = out_dir / name
    reader = RunReader(folder)
    try:
        if fmt == "csv":
            with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
                for f in export_csv(reader, out_dir / "csv"):
                    zf.write(f, f.name)
        elif fmt == "hdf5":
            export_hdf5(reader, path)
        else:
            path.write_text(json.dumps(reader.results(), indent=2), encoding="utf-8")
    finally:
        reader.close()
    return path, name, media


def media_type(name: str) -> str:
    """The media type a download is served with."""
    return DOWNLOADS.get(name) or DOWNLOAD_SUFFIXES.get(
        Path(name).suffix, "application/octet-stream"
    )
