"""What every driver's ``identify()`` returns."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Identity:
    """Model, serial number and firmware version as the device reports them ("" if it cannot),
    and a warning about the identification ("" for none: e.g. a model code its register map
    does not list, accepted for its family)."""

    model: str
    serial: str
    firmware: str
    warning: str = ""
