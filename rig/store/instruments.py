"""The instruments a run used, as its copy of the rig configuration names them: kind, serial and
calibration certificate (``serial``, ``calibrated_on``, ``certificate_expires``: the optional
device keys, docs/lab.md), and whether the certificate had expired when the run started. The
report shows them and the lab index keeps them; both read them here."""

from __future__ import annotations

import datetime as dt
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rig.store import safe_files

MAX_CONFIG_BYTES = 1 << 20
"""A run's rig.toml copy larger than this is not read."""


@dataclass(frozen=True)
class Instrument:
    """A device of the rig configuration the run used, with its certificate dates if given."""

    name: str
    kind: str
    serial: str | None
    calibrated_on: dt.date | None
    certificate_expires: dt.date | None
    expired: bool | None
    """The certificate had expired when the run started (None: no expiry date configured)."""


def config_copy(path: Path) -> dict[str, Any]:
    """A run's copy of the rig configuration ({} when missing or unreadable)."""
    try:
        return tomllib.loads(safe_files.read_text(path, MAX_CONFIG_BYTES))
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError, safe_files.UnsafeFileError):
        return {}


def as_date(value: Any) -> dt.date | None:
    """A TOML date, datetime or ISO 8601 string as a date (None when it is none of them)."""
    if isinstance(value, dt.datetime):
        return value.date()
    if isinstance(value, dt.date):
        return value
    if isinstance(value, str):
        try:
            return dt.date.fromisoformat(value[:10])
        except ValueError:
            return None
    return None


def instruments(config: dict[str, Any], started_at: str | None) -> list[Instrument]:
    """Every device of the configuration copy, its certificate judged against ``started_at``
    (the run's start, ISO 8601)."""
    devices = config.get("devices")
    if not isinstance(devices, dict):
        return []
    start = as_date(started_at)
    out = []
    for name, spec in devices.items():
        if not isinstance(spec, dict):
            continue
        expires = as_date(spec.get("certificate_expires"))
        serial = spec.get("serial")
        out.append(Instrument(
            name=str(name), kind=str(spec.get("kind", "")),
            serial=str(serial) if serial not in (None, "") else None,
            calibrated_on=as_date(spec.get("calibrated_on")), certificate_expires=expires,
            expired=(expires < start) if expires is not None and start is not None else None,
        ))  # fmt: skip
    return out
