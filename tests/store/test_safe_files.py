"""Run-folder files are read and written without following links (rig.store.safe_files)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from rig.store import safe_files
from rig.store.safe_files import UnsafeFileError


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    """A file outside the run folder that an attacker would like read or overwritten."""
    target = tmp_path / "secret.txt"
    target.write_text("do not touch\n")
    return target


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    run = tmp_path / "runs" / "r1"
    run.mkdir(parents=True)
    return run


def test_read_refuses_a_link_and_reads_a_file(folder: Path, outside: Path) -> None:
    (folder / "x.png").symlink_to(outside)
    with pytest.raises(UnsafeFileError, match="symbolic link"):
        safe_files.read_bytes(folder / "x.png")
    (folder / "ok.txt").write_text("fine")
    assert safe_files.read_text(folder / "ok.txt") == "fine"


def test_read_refuses_a_fifo_without_hanging(folder: Path) -> None:
    os.mkfifo(folder / "report.txt")
    with pytest.raises(UnsafeFileError, match="not a regular file"):
        safe_files.read_bytes(folder / "report.txt")


def test_read_bounds_the_size(folder: Path) -> None:
    (folder / "big.bin").write_bytes(b"x" * 1000)
    with pytest.raises(UnsafeFileError, match="larger than 100 bytes"):
        safe_files.read_bytes(folder / "big.bin", max_bytes=100)


def test_write_replaces_the_link_not_its_target(folder: Path, outside: Path) -> None:
    (folder / "report.txt").symlink_to(outside)
    safe_files.write_text(folder / "report.txt", "the report\n")
    assert outside.read_text() == "do not touch\n"
    assert not (folder / "report.txt").is_symlink()
    assert (folder / "report.txt").read_text() == "the report\n"
    assert sorted(p.name for p in folder.iterdir()) == ["report.txt"]  # no temporary left


def test_replacing_by_name_and_failure_leaves_nothing(folder: Path, outside: Path) -> None:
    (folder / "run.h5").symlink_to(outside)
    with pytest.raises(RuntimeError), safe_files.replacing(folder / "run.h5") as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("writer failed")
    assert (folder / "run.h5").is_symlink()  # untouched, and no temporary left
    assert sorted(p.name for p in folder.iterdir()) == ["run.h5"]
    with safe_files.replacing(folder / "run.h5") as tmp:
        tmp.write_bytes(b"hdf5")
    assert outside.read_text() == "do not touch\n"
    assert (folder / "run.h5").read_bytes() == b"hdf5"


def test_private_mode(folder: Path) -> None:
    safe_files.write_text(folder / "secret", "s", mode=0o600)
    assert stat.S_IMODE(os.stat(folder / "secret").st_mode) == 0o600


def test_a_linked_run_folder_is_refused(tmp_path: Path, folder: Path) -> None:
    (tmp_path / "runs" / "r2").symlink_to(folder)
    with pytest.raises(UnsafeFileError, match="symbolic link"):
        safe_files.check_folder(tmp_path / "runs" / "r2")
    with pytest.raises(UnsafeFileError, match="symbolic link"):
        safe_files.write_text(tmp_path / "runs" / "r2" / "report.txt", "x")
    assert not (folder / "report.txt").exists()
    assert safe_files.check_folder(folder) == folder


def test_regular_file_checks(folder: Path, outside: Path) -> None:
    (folder / "run.sqlite").symlink_to(outside)
    with pytest.raises(UnsafeFileError):
        safe_files.regular_file(folder / "run.sqlite")
    assert not safe_files.is_regular_file(folder / "run.sqlite")
    assert safe_files.is_regular_file(outside)
    with pytest.raises(FileNotFoundError):
        safe_files.regular_file(folder / "missing")
