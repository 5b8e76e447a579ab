"""What every driver's ``identify()`` returns."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Identity:
    """Model, serial number and firmware version as the device reports them ("" if it cannot)."""

    model: str
    serial: str
    firmware: str
