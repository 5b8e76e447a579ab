"""Reading a stored step result back as its kind's record: each value checked as it is read,
and a missing or mistyped one named in a :class:`~rig.errors.StoredResultError`.

Values are returned as stored (an int limit stays an int), so a record read from a result gives
back the very mapping it was read from (``to_dict``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeAlias, TypeVar, cast

from rig.errors import StoredResultError

JsonValue: TypeAlias = (
    "str | int | float | bool | Sequence[JsonValue] | Mapping[str, JsonValue] | None"
)
"""What a run's store can keep as JSON (its results and meta): nested mappings and sequences of
strings, numbers, booleans and None."""
JsonObject: TypeAlias = Mapping[str, JsonValue]
"""A step's result or a run meta value as stored: a JSON object."""

R = TypeVar("R")


def read_or_none(from_dict: Callable[[Any], R], result: Any) -> R | None:
    """``from_dict(result)``, or None when the stored result is not that record (the report then
    lists the result's numbers, as for any result its kind does not describe)."""
    try:
        return from_dict(result)
    except StoredResultError:
        return None


def mapping(value: Any, what: str) -> Mapping[str, Any]:
    """``value`` when it is a mapping; else the error naming ``what`` (e.g. "linearity result")."""
    if not isinstance(value, Mapping):
        raise StoredResultError(f"stored {what} is not a mapping: {value!r:.80}")
    return value


def entry(d: Mapping[str, Any], key: str, what: str) -> Any:
    """``d[key]``; the error names the missing key and what was read."""
    if key not in d:
        raise StoredResultError(f"stored {what} has no '{key}' (it has: {', '.join(d) or 'none'})")
    return d[key]


def is_number(value: Any) -> bool:
    """An int or float (not a bool)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def number(d: Mapping[str, Any], key: str, what: str) -> float:
    """``d[key]``, a number (int or float, returned as stored)."""
    value = entry(d, key, what)
    if not is_number(value):
        raise StoredResultError(f"stored {what}: '{key}' must be a number, got {value!r:.80}")
    return cast(float, value)


def optional_number(d: Mapping[str, Any], key: str, what: str) -> float | None:
    """``d[key]``: a number or null (missing reads as null)."""
    return None if d.get(key) is None else number(d, key, what)


def integer(d: Mapping[str, Any], key: str, what: str) -> int:
    """``d[key]``, a whole number stored as an int."""
    value = entry(d, key, what)
    if isinstance(value, bool) or not isinstance(value, int):
        raise StoredResultError(f"stored {what}: '{key}' must be a whole number, got {value!r:.80}")
    return value


def text(d: Mapping[str, Any], key: str, what: str) -> str:
    """``d[key]``, a string."""
    value = entry(d, key, what)
    if not isinstance(value, str):
        raise StoredResultError(f"stored {what}: '{key}' must be text, got {value!r:.80}")
    return value


def numbers(d: Mapping[str, Any], key: str, what: str, n: int | None = None) -> tuple[float, ...]:
    """``d[key]``, a list of numbers (exactly ``n`` when given)."""
    value = entry(d, key, what)
    if not isinstance(value, list) or not all(is_number(v) for v in value):
        raise StoredResultError(
            f"stored {what}: '{key}' must be a list of numbers, got {value!r:.80}"
        )
    if n is not None and len(value) != n:
        raise StoredResultError(f"stored {what}: '{key}' must hold {n} numbers, got {len(value)}")
    return tuple(value)


def matrix3(d: Mapping[str, Any], key: str, what: str) -> tuple[tuple[float, ...], ...]:
    """``d[key]``, a 3x3 list of lists of numbers."""
    rows = entry(d, key, what)
    if not isinstance(rows, list) or len(rows) != 3:
        raise StoredResultError(f"stored {what}: '{key}' must be a 3x3 matrix, got {rows!r:.80}")
    return tuple(numbers({key: row}, key, what, 3) for row in rows)


def number_map(d: Mapping[str, Any], key: str, what: str) -> dict[str, float]:
    """``d[key]``, a mapping of names to numbers."""
    value = mapping(entry(d, key, what), f"{what} '{key}'")
    return {str(k): number(value, k, f"{what} '{key}'") for k in value}
