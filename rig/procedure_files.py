"""The shipped procedure library (``rig/shipped_procedures/``, installed with the package) and
finding a procedure or a target set by path or name."""

from __future__ import annotations

from pathlib import Path

from rig.errors import UserInputError

PROCEDURES_DIR = Path(__file__).resolve().parent / "shipped_procedures"
TARGETS_DIR = PROCEDURES_DIR / "targets"


def find_procedure(name: str) -> Path:
    """A procedure by path, or by name in ``rig/shipped_procedures/``."""
    return _find(name, PROCEDURES_DIR, "procedure")


def find_targets(name: str) -> Path:
    """A target set for ``rig design`` by path, or by name in ``rig/shipped_procedures/targets/``."""
    return _find(name, TARGETS_DIR, "target set")


def _find(name: str, folder: Path, what: str) -> Path:
    p = Path(name)
    if p.exists():
        return p
    shipped = folder / (name if name.endswith(".yaml") else f"{name}.yaml")
    if shipped.exists():
        return shipped
    names = ", ".join(sorted(f.stem for f in folder.glob("*.yaml")))
    raise UserInputError(f"no {what} '{name}': give a path or one of: {names}")


def shipped_name(path: Path) -> str:
    """A shipped file's path as it reads in the source tree (``rig/shipped_procedures/...``),
    wherever the package is installed."""
    return str(Path("rig") / path.relative_to(PROCEDURES_DIR.parent))
