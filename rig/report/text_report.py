"""What the three renderings of the report share: the data digest, the seal note, the overall
verdict and a criterion's value, limits and margin as text."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rig.analysis import value_unit
from rig.store.run_states import ACCEPTANCE, RunStatus, Verdict
from rig.store.seal import data_digest, read_seal
from rig.verdict import CriterionResult, check_verdict


def data_hash(folder: Path) -> str:
    """The run's data digest (SHA-256 of its rows, see :mod:`rig.store.seal`), recomputed."""
    return data_digest(folder / "run.sqlite")[0]


def seal_note(folder: Path, digest: str) -> str:
    """How ``digest`` compares with the run's seal, for the report header."""
    seal = read_seal(folder)
    if seal is None:
        return "not sealed (the run was still running, or recorded before runs were sealed)"
    if seal.get("data_sha256") != digest:
        return f"DATA CHANGED SINCE THE RUN WAS SEALED (sealed {seal.get('data_sha256')})"
    return f"matches the seal of {seal.get('sealed_at')}"


def overall_verdict(meta: dict[str, Any], results: dict[str, Any]) -> str:
    """PASS, FAIL, RE-RUN or NO VERDICT for a closed run; a run that did not finish is never an
    acceptance, and one whose data failed the timing checks is judged neither way."""
    status = meta.get("status", RunStatus.INCOMPLETE)
    verdict = check_verdict(results)
    if status == RunStatus.RERUN:
        rerun = verdict.rerun if verdict is not None else ()
        why = "; ".join(f"{result}: {why}" for result, why in rerun) or meta.get("reason", "")
        return f"{Verdict.RERUN} - NOT JUDGED, RUN AGAIN ({why})"
    if status not in ACCEPTANCE:
        return f"{str(status).upper()} RUN - NOT A VALID ACCEPTANCE"
    return str(verdict.overall) if verdict is not None else "NO VERDICT"


def limit_text(row: CriterionResult) -> tuple[str, str, str]:
    """(value, limits, margin) of one criterion row with a value, with its unit."""
    unit = row.unit
    if unit is None:  # recorded before rows carried their unit
        unit = value_unit(row.name)
    u = f" {unit}" if unit else ""
    bounds = [
        f"{what} {v:g}{u}" for what, v in (("min", row.min), ("max", row.max)) if v is not None
    ]
    limits = ", ".join(bounds) or "no limit"
    margin = "" if row.margin is None else f"{row.margin:.3g}{u}"
    if row.uncertainty is None:
        return f"{row.value:.4g}{u}", limits, margin
    return f"{row.value:.6g} +- {row.uncertainty:.2g}{u} (k=2)", limits, f"{margin} after U"
