"""The cage model ``B = K I + B0`` and its versioned calibration file."""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

import timebase
from rig.errors import UserInputError

Array = npt.NDArray[np.float64]
SCHEMA = "rig.cage-calibration/1"


@dataclass(frozen=True)
class CageModel:
    """Field at the DUT (uT, cage frame) from coil currents (A): ``B = K I + B0``.

    ``k_sigma``/``b0_sigma_ut`` are 1-sigma uncertainties from the characterization (zeros for a
    nominal model); ``meta`` records date, instruments and residuals.
    """

    k_ut_per_a: Array
    b0_ut: Array
    k_sigma: Array = field(default_factory=lambda: np.zeros((3, 3)))
    b0_sigma_ut: Array = field(default_factory=lambda: np.zeros(3))
    meta: dict[str, Any] = field(default_factory=dict)

    def field_ut(self, currents_a: npt.ArrayLike) -> Array:
        """Field for coil currents."""
        return np.asarray(self.k_ut_per_a @ np.asarray(currents_a, float) + self.b0_ut)

    def currents_a(self, field_ut: npt.ArrayLike) -> Array:
        """Coil currents that produce ``field_ut`` (solves the full 3x3 coupling)."""
        return np.asarray(
            np.linalg.solve(self.k_ut_per_a, np.asarray(field_ut, float) - self.b0_ut)
        )

    def to_dict(self) -> dict[str, Any]:
        """The calibration file's content."""
        return {
            "schema": SCHEMA,
            "k_ut_per_a": self.k_ut_per_a.tolist(),
            "b0_ut": self.b0_ut.tolist(),
            "k_sigma_ut_per_a": self.k_sigma.tolist(),
            "b0_sigma_ut": self.b0_sigma_ut.tolist(),
            **self.meta,
        }

    def with_metrology(self, kind: str, entry: dict[str, Any]) -> CageModel:
        """This model with a metrology result added under ``kind`` (a step kind: ``coil_axes``,
        ``field_map``, ``supply_stability``), replacing an older one of that kind; ``entry``
        carries its ``date`` (ISO UTC) and ``run`` (the run folder it came from)."""
        metrology = dict(self.meta.get("metrology") or {})
        metrology[kind] = entry
        meta = {**self.meta, "metrology": metrology, "updated": entry.get("date")}
        return CageModel(self.k_ut_per_a, self.b0_ut, self.k_sigma, self.b0_sigma_ut, meta)

    def metrology(self) -> dict[str, dict[str, Any]]:
        """The metrology results the record holds, by step kind (empty for none)."""
        found = self.meta.get("metrology")
        return dict(found) if isinstance(found, dict) else {}

    def save(self, path: str | Path) -> Path:
        """Write a new version next to ``path`` (``name.YYYYMMDDTHHMMSS.json``, stamped with the
        latest of its date and its metrology's) and point ``path`` at it.

        Old versions are never overwritten (a second version of the same second gets ``-2``, ...);
        ``path`` itself is replaced atomically.
        """
        path = Path(path)
        now = dt.datetime.fromtimestamp(timebase.wall_time(), dt.UTC).isoformat(timespec="seconds")
        stamp = max((str(d) for d in (self.meta.get("date"), self.meta.get("updated")) if d),
                    default=now)  # fmt: skip
        base = f"{path.stem}.{stamp.replace(':', '').replace('-', '')[:15]}"
        version = path.with_name(f"{base}{path.suffix}")
        n = 1
        while version.exists():
            n += 1
            version = path.with_name(f"{base}-{n}{path.suffix}")
        text = json.dumps(self.to_dict(), indent=2) + "\n"
        path.parent.mkdir(parents=True, exist_ok=True)
        version.write_text(text, encoding="utf-8")
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(path)
        return version

    @staticmethod
    def load(path: str | Path) -> CageModel:
        """Read a calibration file; one-line errors for anything wrong with it."""
        path = Path(path)
        try:
            raw = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise UserInputError(
                f"{path}: no such cage calibration; run the cage characterization first"
            ) from None
        except json.JSONDecodeError as exc:
            raise UserInputError(
                f"{path}: not valid JSON (line {exc.lineno}): restore it from a saved version"
            ) from None
        if raw.get("schema") != SCHEMA:
            raise UserInputError(f"{path}: schema {raw.get('schema')!r} is not {SCHEMA!r}")
        try:
            k = np.array(raw["k_ut_per_a"], float).reshape(3, 3)
            b0 = np.array(raw["b0_ut"], float).reshape(3)
        except (KeyError, ValueError) as exc:
            raise UserInputError(f"{path}: missing or malformed {exc}") from None
        if abs(np.linalg.det(k)) < 1e-9:
            raise UserInputError(f"{path}: coil matrix is singular; recharacterize the cage")
        meta = {
            k_: v
            for k_, v in raw.items()
            if k_ not in ("k_ut_per_a", "b0_ut", "k_sigma_ut_per_a", "b0_sigma_ut")
        }
        return CageModel(k, b0, np.array(raw.get("k_sigma_ut_per_a", np.zeros((3, 3))), float),
                         np.array(raw.get("b0_sigma_ut", np.zeros(3)), float), meta)  # fmt: skip
