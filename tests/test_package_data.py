"""What a plain ``pip install .`` (not editable) installs is the whole product: every file of the
five packages that the source tree holds, the shipped procedures and the simulator's default cage
included (before, a bench installed that way had neither: ``rig check smoke`` answered "no
procedure 'smoke'")."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("rig", "drivers", "sim", "regmaps", "timebase")


def source_files() -> set[str]:
    """The product's files in the source tree (git's list where there is one)."""
    try:
        listed = subprocess.run(["git", "ls-files", *PACKAGES], cwd=ROOT, capture_output=True,
                                text=True, check=True).stdout.split()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        listed = [str(p.relative_to(ROOT)) for pkg in PACKAGES for p in (ROOT / pkg).rglob("*")
                  if p.is_file() and "__pycache__" not in p.parts]  # fmt: skip
    return set(listed)


def test_the_wheel_holds_every_file_of_the_packages(tmp_path: Path) -> None:
    tree = tmp_path / "src"
    shutil.copytree(ROOT, tree, ignore=shutil.ignore_patterns(
        ".venv", "build", "dist", "*.egg-info", "__pycache__", ".git", "runs", ".*_cache"))  # fmt: skip
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                            str(tmp_path / "dist"), str(tree)],
                           capture_output=True, text=True, timeout=600)  # fmt: skip
    assert built.returncode == 0, built.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("*.whl")
    in_wheel = set(zipfile.ZipFile(wheel).namelist())
    missing = sorted(source_files() - in_wheel)
    assert not missing, f"not installed by 'pip install .' (pyproject package-data): {missing}"
    assert "rig/shipped_procedures/dut-acceptance.yaml" in in_wheel
    assert "sim/default_cage.toml" in in_wheel
