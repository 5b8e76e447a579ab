"""The one rule for text that lands in a run's record: names, serials, titles, free text.

Whatever a procedure, a ``--set`` or a rig configuration gives - a procedure's title, its step
and parameter names and values (DUT serial, lot, operator), device names and serials - is copied
into the run's metadata, its report and the lab index. There a NUL byte broke every later sync of
the lab index and a 300-character serial made the run folder's name too long (issue 29). So:

* **no control characters**: C0 (U+0000-U+001F), DEL (U+007F) and C1 (U+0080-U+009F) are
  refused, except tab and line feed in free text (a prompt's text, a description: what a step
  kind declares ``Param(text="free")``) and tab in a rig configuration's values (a ``delimiter``);
* **labels** (every name, serial, title and parameter value) are at most :data:`MAX_TEXT_CHARS`
  characters; free text, paths, host names and URLs have no limit of their own.

The procedure language (:mod:`rig.procedure.language`, ``--set`` included) and the configuration
loader (:mod:`rig.config`) ask :func:`text_problem`; each names the file, line or key.
"""

from __future__ import annotations

MAX_TEXT_CHARS = 128
"""Longest label (characters): a DUT serial, lot, operator, title, step, parameter or device name."""

FREE_TEXT_CONTROLS = "\t\n"
"""Control characters free text may hold (tab, line feed)."""


def is_control(ch: str) -> bool:
    """C0, DEL or C1: a character that is not text."""
    code = ord(ch)
    return code < 0x20 or 0x7F <= code <= 0x9F


def _named(ch: str) -> str:
    code = ord(ch)
    name = {0: "NUL", 9: "tab", 10: "line feed", 13: "carriage return", 27: "ESC", 127: "DEL"}
    return f"U+{code:04X}" + (f" {name[code]}" if code in name else "")


def text_problem(value: str, *, label: bool = True, allowed: str = "") -> str | None:
    """What is wrong with ``value`` as a clause ending with the fix, None when it is fine.

    ``label``: a name, serial or title (at most :data:`MAX_TEXT_CHARS` characters, no control
    character); else free text. ``allowed``: control characters it may hold all the same (tab,
    line feed: :data:`FREE_TEXT_CONTROLS`)."""
    for i, ch in enumerate(value):
        if is_control(ch) and ch not in allowed:
            return (
                f"holds the control character {_named(ch)} at character {i + 1}, which a run's"
                " record, report and lab index cannot keep: remove it"
            )
    if label and len(value) > MAX_TEXT_CHARS:
        return (
            f"is {len(value)} characters long, beyond the {MAX_TEXT_CHARS} a name, serial or"
            " title may have (MAX_TEXT_CHARS): shorten it"
        )
    return None


def shown(value: str, limit: int = 32) -> str:
    """``value`` safe to print in a one-line error: control characters escaped, cut at ``limit``."""
    out = "".join(f"\\x{ord(c):02x}" if is_control(c) else c for c in value[:limit])
    return f"'{out}...'" if len(value) > limit else f"'{out}'"
