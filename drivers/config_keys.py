"""The configuration-key type system: one :class:`Param` per key of a rig configuration (a device's,
the ``[cage]`` or the ``[lab]`` table), its accepted types and values, and the words a user reads
when a value is wrong. The device kinds (:mod:`drivers.registry`) and the rig's own tables
(``rig.config``) declare their keys with it; ``docs/devices.md``'s key tables are generated from
those declarations.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass
from typing import Any

TEXT: tuple[type, ...] = (str,)
WHOLE: tuple[type, ...] = (int,)
NUMBER: tuple[type, ...] = (int, float)
LIST: tuple[type, ...] = (list,)
WHOLE_OR_TEXT: tuple[type, ...] = (int, str)
DATE: tuple[type, ...] = (dt.date,)
TABLE: tuple[type, ...] = (dict,)
WANTED = {TEXT: "text", WHOLE: "a whole number", NUMBER: "a number", LIST: "a list",
          WHOLE_OR_TEXT: "a whole number (or \"sim\")", DATE: "a TOML date (2026-01-15, no quotes)",
          TABLE: "a table"}  # fmt: skip


STANDARD_BAUDRATES: tuple[int, ...] = (
    300, 600, 1200, 2400, 4800, 9600, 14400, 19200, 28800, 38400, 57600, 76800, 115200, 128000,
    230400, 250000, 256000, 460800, 500000, 921600, 1000000, 1500000, 2000000,
)  # fmt: skip
"""Baud rates a serial port or USB adapter offers; anything else is a typing mistake."""


@dataclass(frozen=True)
class Param:
    """One configuration key (of a device, the ``[cage]`` or the ``[lab]`` table): its accepted
    types, whether it must be given, its default (filled in when the key is absent; None: no
    default), a short help text and its ``unit`` (shown in errors and in ``docs/devices.md``), and
    the values it accepts.

    The accepted values are stated here and nowhere else: ``low``/``high`` (inclusive bounds),
    ``above`` (an exclusive lower bound, e.g. 0 for a timeout), ``choices`` (a list of the
    accepted values) and ``nonempty`` (text). Every number must be finite. ``why`` explains a
    range in an error, ``fix`` says what to write instead.
    """

    name: str
    types: tuple[type, ...]
    required: bool = False
    default: Any = None
    help: str = ""
    low: float | None = None
    high: float | None = None
    above: float | None = None
    choices: tuple[Any, ...] = ()
    nonempty: bool = False
    why: str = ""
    fix: str = ""
    unit: str = ""
    shape: tuple[int, ...] = ()
    """For a list: its shape of finite numbers ((3,): three; (3, 3): three rows of three)."""

    @property
    def wanted(self) -> str:
        """How to describe the accepted type to a user ("a whole number")."""
        return WANTED.get(self.types, " or ".join(t.__name__ for t in self.types))

    @property
    def accepted(self) -> str:
        """The accepted values in words ("1-65535", "N, E or O", "more than 0"), "" if any."""
        if self.choices:
            words = [str(c) for c in self.choices]
            return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} or {words[-1]}"
        if self.low is not None and self.high is not None:
            return f"{_num(self.low)}-{_num(self.high)}"
        if self.above is not None:
            return f"more than {_num(self.above)}"
        if self.low is not None:
            return f"at least {_num(self.low)}"
        if self.high is not None:
            return f"at most {_num(self.high)}"
        return ""

    def accepts(self, value: Any) -> bool:
        """True when ``value`` has an accepted type (booleans are not numbers)."""
        return not isinstance(value, bool) and isinstance(value, self.types)

    def problem(self, value: Any) -> str | None:
        """What is wrong with ``value`` in one clause that ends with the fix; None when it is
        fine. For example ``"70000 is outside 1-65535 (a TCP port); write the port ..."``."""
        if not self.accepts(value):
            return f"must be {self.wanted}, got {value!r}"
        fix = f"; {self.fix}" if self.fix else ""
        why = f" ({self.why})" if self.why else ""
        if isinstance(value, list):
            if self.shape and not _has_shape(value, self.shape):
                what = (f"a list of {self.shape[0]} finite numbers" if len(self.shape) == 1 else
                        f"{' x '.join(map(str, self.shape))} finite numbers (a list of lists)")  # fmt: skip
                return f"must be {what}, got {value!r}{fix}"
            return None
        if isinstance(value, str):
            if self.nonempty and not value.strip():
                return f"must not be empty{fix}"
            if self.choices and value not in self.choices:
                return f"{value!r} is not {self.why or 'one of'}: {self.accepted}{fix}"
            return None
        if not isinstance(value, int | float):
            return None
        if not math.isfinite(value):
            return f"{value} is not a finite number{fix or '; write a number'}"
        if self.choices and value not in self.choices:
            near = _nearest(value, self.choices)
            return f"{_num(value)} is not {self.why or 'one of'}{near}: {self.accepted}{fix}"
        if (self.low is not None and value < self.low) or (
            self.high is not None and value > self.high
        ):
            return f"{_num(value)} is outside {self.accepted}{why}{fix}"
        if self.above is not None and value <= self.above:
            return f"must be {self.accepted}, got {_num(value)}{why}{fix}"
        return None


def _has_shape(value: Any, shape: tuple[int, ...]) -> bool:
    """True when ``value`` is nested lists of ``shape`` holding finite numbers (not booleans)."""
    if not shape:
        return (isinstance(value, int | float) and not isinstance(value, bool)
                and math.isfinite(value))  # fmt: skip
    return (isinstance(value, list) and len(value) == shape[0]
            and all(_has_shape(v, shape[1:]) for v in value))  # fmt: skip


def _num(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else str(value)


def _nearest(value: float, choices: tuple[Any, ...]) -> str:
    """A hint like ``" (did you mean 115200?)"`` for a digit too many or too few, or a value
    within 5 % of one of ``choices``; "" otherwise."""
    numbers = [c for c in choices if isinstance(c, int | float) and c > 0]
    for c in numbers:
        if value > 0 and (value * 10 == c or value == c * 10 or abs(value / c - 1) <= 0.05):
            return f" (did you mean {_num(c)}?)"
    return ""
