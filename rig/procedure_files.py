"""The shipped procedure library (``procedures/``) and finding a procedure by path or name."""

from __future__ import annotations

from pathlib import Path

from rig.errors import UserInputError

PROCEDURES_DIR = Path(__file__).resolve().parent.parent / "procedures"


def find_procedure(name: str) -> Path:
    """A procedure by path, or by name in the shipped ``procedures/`` folder."""
    p = Path(name)
    if p.exists():
        return p
    shipped = PROCEDURES_DIR / (name if name.endswith(".yaml") else f"{name}.yaml")
    if shipped.exists():
        return shipped
    names = ", ".join(sorted(f.stem for f in PROCEDURES_DIR.glob("*.yaml")))
    raise UserInputError(f"no procedure '{name}': give a path or one of: {names}")
