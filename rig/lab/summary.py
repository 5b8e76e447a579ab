"""One closed run as the lab index holds it, read from its folder (store, seal, configuration copy).

Units: criteria carry their own (``unit``); calibration results are as in the result file (offsets
uT, scale factors 1, angles deg, residual rms nT); times are ISO 8601 UTC strings.
"""

from __future__ import annotations

import math
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rig.errors import StoredResultError
from rig.lab.url import rig_name
from rig.store import safe_files
from rig.store.instruments import Instrument, config_copy, instruments
from rig.store.run_states import RunStatus
from rig.store.run_store import RunReader
from rig.store.seal import REPORT_FILES, read_seal
from rig.verdict import CheckVerdict, check_verdict

UNSEALED = "unsealed"
"""The hash part of the key of a closed run that has no seal (recorded before seals existed)."""


@dataclass(frozen=True)
class Criterion:
    """An acceptance criterion: value and limits in ``unit``; margin to the nearest limit (same
    unit, positive inside the limits, None without a value or limits)."""

    name: str
    value: float | None
    unit: str
    min: float | None
    max: float | None
    margin: float | None
    verdict: str


@dataclass(frozen=True)
class Result:
    """A calibration parameter of a step's result (``source`` = the step's name) with its 1-sigma."""

    source: str
    name: str
    value: float
    sigma: float | None


@dataclass(frozen=True)
class RunSummary:
    """What the lab index holds about one closed run; ``uid`` is its idempotency key."""

    run_id: str
    data_sha256: str | None
    rig: str
    host: str | None
    procedure: str | None
    dut_serial: str | None
    lot: str | None
    operator: str | None
    status: str
    verdict: str | None
    started_at: str | None
    sealed_at: str | None
    software_version: str | None
    report_files: list[str]
    instruments: list[Instrument] = field(default_factory=list)
    criteria: list[Criterion] = field(default_factory=list)
    results: list[Result] = field(default_factory=list)

    @property
    def uid(self) -> str:
        """``<run id>:<data sha256>``: the same run synced twice (from anywhere) is one row."""
        return run_key(self.run_id, self.data_sha256)


def run_key(run_id: str, data_sha256: str | None) -> str:
    """The index key of a run: its folder name and its data hash."""
    return f"{run_id}:{data_sha256 or UNSEALED}"


def sealed_key(folder: Path) -> str | None:
    """The key from ``seal.json`` alone (no database opened), None when the run has no seal."""
    seal = read_seal(folder)
    sha = seal.get("data_sha256") if seal else None
    return run_key(folder.name, str(sha)) if isinstance(sha, str) and len(sha) == 64 else None


def summarize(folder: Path) -> RunSummary | None:
    """The summary of a closed run; None while it is still running (its owner alive).

    Opening the store marks a killed run incomplete and seals it, as ``rig runs`` does.
    """
    reader = RunReader(folder)
    try:
        meta, results = reader.meta(), reader.results()
    finally:
        reader.close()
    status = str(meta.get("status", RunStatus.INCOMPLETE))
    if status == RunStatus.RUNNING:
        return None
    seal = read_seal(folder) or {}
    sha = seal.get("data_sha256")
    config = config_copy(folder / "rig.toml")
    given = meta.get("parameters")
    params: dict[str, Any] = given if isinstance(given, dict) else {}
    started = _str(meta.get("start_time"))
    verdict = stored_verdict(results)
    return RunSummary(
        run_id=folder.name,
        data_sha256=sha if isinstance(sha, str) and len(sha) == 64 else None,
        rig=rig_name(config) or _str(meta.get("host")) or socket.gethostname(),
        host=_str(meta.get("host")),
        procedure=_str(meta.get("procedure")),
        dut_serial=_str(meta.get("dut_serial")) or _str(params.get("dut_serial")),
        lot=_str(params.get("lot")),
        operator=_str(meta.get("operator")) or _str(params.get("operator")),
        status=status,
        verdict=str(verdict.overall) if verdict is not None else None,
        started_at=started,
        sealed_at=_str(seal.get("sealed_at")),
        software_version=_str(meta.get("software_version")),
        report_files=[n for n in REPORT_FILES if safe_files.is_regular_file(folder / n)],
        instruments=instruments(config, started),
        criteria=criteria(verdict),
        results=calibration_results(results),
    )


def _str(value: Any) -> str | None:
    return str(value) if value not in (None, "") else None


def _number(value: Any) -> float | None:
    """A stored number as a float (an infinite or huge one kept, for the sync's range check to
    refuse, :mod:`rig.lab.bounds`); None for NaN or anything not a number."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        x = float(value)
    except OverflowError:  # an integer beyond any float
        return math.inf if value > 0 else -math.inf
    return None if math.isnan(x) else x


def stored_verdict(results: dict[str, Any]) -> CheckVerdict | None:
    """The run's check verdict; None without one, or when it cannot be read as one (a run folder
    from elsewhere is indexed without it rather than refused)."""
    try:
        return check_verdict(results)
    except StoredResultError:
        return None


def criteria(verdict: CheckVerdict | None) -> list[Criterion]:
    """The acceptance criteria of the run's verdict, with the margin to the nearest limit."""
    out = []
    for row in verdict.criteria if verdict is not None else ():
        value, lo, hi = _number(row.value), _number(row.min), _number(row.max)
        gaps = [] if value is None else [g for g in (
            None if lo is None else value - lo, None if hi is None else hi - value) if g is not None]  # fmt: skip
        out.append(Criterion(row.name, value, row.unit or "", lo, hi,
                             min(gaps) if gaps else None, str(row.verdict)))  # fmt: skip
    return out


def calibration_results(results: dict[str, Any]) -> list[Result]:
    """The parameters of every calibration result (Springmann parameters with their sigma, and
    the residual rms in nT)."""
    out = []
    for source, value in sorted(results.items()):
        if not isinstance(value, dict) or not isinstance(value.get("springmann"), dict):
            continue
        sigma_all = value.get("sigma")
        sigmas = sigma_all.get("springmann", {}) if isinstance(sigma_all, dict) else {}
        for name, v in value["springmann"].items():
            if (x := _number(v)) is not None:
                s = _number(sigmas.get(name)) if isinstance(sigmas, dict) else None
                out.append(Result(source, str(name), x, s))
        if (rms := _number(value.get("residual_rms_nt"))) is not None:
            out.append(Result(source, "residual_rms_nt", rms, None))
    return out
