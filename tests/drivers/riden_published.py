"""The Riden RD60xx model table as published by others, typed in from their sources (not from the
project's driver or simulator), for the tests of both.

Sources, each read at the version named in docs/devices.md:
  S  ShayBox/Riden ``riden/riden.py`` (Python client): id ranges and the v/i/p multipliers;
     the RD6012P's i_multi is 10000 when register 20 (I_RANGE) reads 0, else 1000.
  L  libsigrok ``src/hardware/rdtech-dps/api.c`` (model table): ids and digits, RD6012P
     "up to 6A with 4 digits (when RTU reg 20 == 0), up to 12A with 3 digits (reg 20 == 1)".
  D  morgendagen/riden-dongle ``src/riden_modbus/riden_modbus.cpp`` (firmware): id ranges,
     multipliers, i_max.
  J  an independent Java client's KNOWN_DEVICE_IDS (RidenRD60xx.java): 60066 RK6006,
     RD6024 60240-60244, RD6030 60300-60304.
"""

from __future__ import annotations

from typing import NamedTuple


class Published(NamedTuple):
    """One model: every id listed for it, V/count, W/count, A/count per range, A max per range."""

    name: str
    ids: tuple[int, ...]
    v_per_count: float
    w_per_count: float
    a_per_count: tuple[float, ...]
    i_max_a: tuple[float, ...]
    sources: str


def _r(a: int, b: int) -> tuple[int, ...]:
    return tuple(range(a, b + 1))


PUBLISHED: tuple[Published, ...] = (
    Published("RD6006", _r(60060, 60064), 0.01, 0.01, (0.001,), (6.0,), "S D L(60061,60062) J"),
    Published("RD6006P", (60065,), 0.001, 0.001, (0.0001,), (6.0,), "S D L J"),
    Published("RK6006", (60066,), 0.01, 0.01, (0.001,), (6.0,), "J"),
    Published("RD6012", _r(60120, 60124), 0.01, 0.01, (0.01,), (12.0,), "S D L(60121) J"),
    Published(
        "RD6012P",
        _r(60125, 60129),
        0.001,
        0.001,
        (0.0001, 0.001),
        (6.0, 12.0),
        "S L(60125) J(60125)",
    ),
    Published("RD6018", _r(60180, 60189), 0.01, 0.01, (0.01,), (18.0,), "S D L(60181) J(-60184)"),
    Published("RD6024", _r(60240, 60244), 0.01, 0.01, (0.01,), (24.0,), "S(>=60241) D L(60241) J"),
    Published("RD6030", _r(60300, 60304), 0.01, 0.01, (0.01,), (30.0,), "D(60301) J"),
)

NOT_RIDEN_IDS = (0, 6006, 60059, 60067, 60119, 60130, 60179, 60190, 60209, 60245, 60299, 60305)
"""Ids no table lists: refused, never guessed."""
