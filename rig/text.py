"""The one rule for text that lands in a run's record: names, serials, titles, free text.

Whatever a procedure, a ``--set`` or a rig configuration gives - a procedure's title, its step
and parameter names and values (DUT serial, lot, operator), device names and serials - is copied
into the run's metadata, its report and the lab index. There a NUL byte broke every later sync of
the lab index and a 300-character serial made the run folder's name too long (issue 29). So:

* **no control characters**: C0 (U+0000-U+001F), DEL (U+007F) and C1 (U+0080-U+009F) are
  refused, except tab and line feed in free text (a prompt's text, a description: what a step
  kind declares ``StepParam(text="free")``) and tab in a rig configuration's values (a ``delimiter``);
* **labels** (every name, serial, title and parameter value) are at most :data:`MAX_TEXT_CHARS`
  characters; free text, paths, host names and URLs have no limit of their own;
* **no invisible characters in labels** (issue 51): the bidirectional controls (embeddings,
  overrides, isolates, marks: U+202A-U+202E, U+2066-U+2069, U+200E, U+200F, U+061C) and the
  zero-width characters (U+200B-U+200D, U+2060, U+FEFF) let a label look like another one (a
  right-to-left override shows the serial ``SN-1<RLO>01`` as ``SN-110``): refused with the
  character's name. Free text keeps them (a right-to-left script needs its marks), but
  :func:`shown` escapes them in every error line.

The procedure language (:mod:`rig.procedure.language`, ``--set`` included) and the configuration
loader (:mod:`rig.config`) ask :func:`text_problem`; each names the file, line or key.
"""

from __future__ import annotations

import unicodedata

MAX_TEXT_CHARS = 128
"""Longest label (characters): a DUT serial, lot, operator, title, step, parameter or device name."""

FREE_TEXT_CONTROLS = "\t\n"
"""Control characters free text may hold (tab, line feed)."""


INVISIBLE = frozenset(
    [chr(c) for c in range(0x202A, 0x202F)]  # LRE, RLE, PDF, LRO, RLO
    + [chr(c) for c in range(0x2066, 0x206A)]  # LRI, RLI, FSI, PDI
    + ["\u200e", "\u200f", "\u061c"]  # LRM, RLM, ALM
    + ["\u200b", "\u200c", "\u200d", "\u2060", "\ufeff"]  # zero width: space, (non-)joiner, WJ, BOM
)
"""Bidirectional controls and zero-width characters: refused in labels (they spoof what a label shows)."""


def is_invisible(ch: str) -> bool:
    """A bidirectional control or zero-width character (:data:`INVISIBLE`)."""
    return ch in INVISIBLE


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
    if label:
        for i, ch in enumerate(value):
            if ch in INVISIBLE:
                return (
                    f"holds the invisible character U+{ord(ch):04X} {unicodedata.name(ch)} at"
                    f" character {i + 1}, which makes a name, serial or title look like another"
                    " one: remove it"
                )
    if label and len(value) > MAX_TEXT_CHARS:
        return (
            f"is {len(value)} characters long, beyond the {MAX_TEXT_CHARS} a name, serial or"
            " title may have (MAX_TEXT_CHARS): shorten it"
        )
    return None


def shown(value: str, limit: int = 32) -> str:
    """``value`` safe to print in a one-line error: control and invisible characters escaped (``\\x1b``,
    ``\\u202e``), cut at ``limit``."""
    out = "".join(
        f"\\x{ord(c):02x}" if is_control(c) else f"\\u{ord(c):04x}" if c in INVISIBLE else c
        for c in value[:limit]
    )
    return f"'{out}...'" if len(value) > limit else f"'{out}'"
