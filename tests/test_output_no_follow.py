"""User-named output files are written without following links (issue 51): ``rig calibrate
--out/--c-header/--px4/--history``, ``rig example-data`` and ``rig design --out`` wrote through a
link another account planted (a dangling one even created its target). Each now refuses a link in
one line (exit 2) naming the path and the fix, before any work and before any other file is
written; the target is left alone and a dangling link's target is not created."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from rig.calibration.synthetic import RAX_CHANNELS
from rig.cli import main
from rig.errors import UserInputError
from rig.io.output_files import write_output

SPHERE = Path(__file__).resolve().parent / "data" / "real-magnetometer" / "space-denpa-set1.csv"
SPHERE_ARGS = ["--measured", "x,y,z", "--unit", "G", "--field-magnitude", "0.47"]
RAX_ARGS = ["--measured", "mx_ut,my_ut,mz_ut", "--field-magnitude", "b_ut", "--telemetry",
            ",".join(RAX_CHANNELS), "--noise-nt", "100"]  # fmt: skip


@pytest.fixture(scope="module")
def rax_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("data") / "rax.csv"
    assert main(["-q", "example-data", str(path), "--samples", "1500", "--seed", "4"]) == 0
    return path


def design_args(tmp_path: Path, out: Path) -> list[str]:
    from tests.test_design import targets
    from tests.test_prediction import RIG

    (tmp_path / "rig.toml").write_text(RIG)
    return ["design", "--targets", str(targets(tmp_path)), "--rig", str(tmp_path / "rig.toml"),
            "--noise-nt", "20", "--out", str(out)]  # fmt: skip


COMMANDS: dict[str, Callable[[Path, Path, Path], list[str]]] = {
    "calibrate --out": lambda csv, tmp, out: ["calibrate", str(csv), *RAX_ARGS, "--out", str(out)],
    "calibrate --c-header": lambda csv, tmp, out: ["calibrate", str(csv), *RAX_ARGS,
                                                   "--out", str(tmp / "ok.json"),
                                                   "--c-header", str(out)],
    "calibrate --px4": lambda csv, tmp, out: ["calibrate", str(SPHERE), *SPHERE_ARGS,
                                              "--out", str(tmp / "ok.json"), "--px4", str(out)],
    "calibrate --history": lambda csv, tmp, out: ["calibrate", str(csv), *RAX_ARGS,
                                                  "--method", "ekf", "--out", str(tmp / "ok.json"),
                                                  "--history", str(out)],
    "example-data": lambda csv, tmp, out: ["example-data", str(out), "--samples", "200"],
    "design --out": lambda csv, tmp, out: design_args(tmp, out),
}  # fmt: skip


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "internal error" not in err and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("dangling", [False, True], ids=["link-to-a-file", "dangling-link"])
def test_a_planted_link_is_refused_and_its_target_left_alone(
    command: str, dangling: bool, rax_csv: Path, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    victim = tmp_path / "victim" / "bashrc"
    victim.parent.mkdir()
    if not dangling:
        victim.write_text("the other account's file\n")
    out = tmp_path / "out" / "result.file"
    out.parent.mkdir()
    out.symlink_to(victim)
    capsys.readouterr()
    assert main(COMMANDS[command](rax_csv, tmp_path, out)) == 2
    err = one_line(capsys.readouterr().err)
    assert f"{out}: is a symbolic link" in err and "choose another file name" in err, err
    assert out.is_symlink()
    if dangling:
        assert not victim.exists()  # a dangling link's target is not created
    else:
        assert victim.read_text() == "the other account's file\n"
    assert not (tmp_path / "ok.json").exists()  # refused before any file was written
    assert [p.name for p in out.parent.iterdir()] == ["result.file"]  # no temporary file left


@pytest.mark.parametrize("command", ["calibrate --out", "example-data"])
def test_a_plain_file_is_replaced_atomically_keeping_its_permissions(
    command: str, rax_csv: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out.file"
    out.write_text("old\n")
    out.chmod(0o600)
    assert main(["-q", *COMMANDS[command](rax_csv, tmp_path, out)]) == 0
    assert out.read_text() != "old\n" and (out.stat().st_mode & 0o777) == 0o600
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_a_fifo_named_as_output_is_refused_without_hanging(tmp_path: Path) -> None:
    """A FIFO there made the old writer wait for a reader forever (here: 60 s, then a failure)."""
    out = tmp_path / "out.csv"
    os.mkfifo(out)
    done = subprocess.run([sys.executable, "-m", "rig.cli", "example-data", str(out), "--samples",
                           "200"], capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2
    assert "is not a regular file (a folder, FIFO or device)" in one_line(done.stderr)


# --- user-named output files (issue 51): refused through a link, written atomically ------------


def test_write_output_refuses_links_and_keeps_targets(tmp_path: Path) -> None:
    outside = tmp_path / "secret.txt"
    outside.write_text("do not touch\n")
    out = tmp_path / "result.json"
    out.symlink_to(outside)
    with pytest.raises(UserInputError, match=r"result\.json: is a symbolic link.*remove it or"
                       r" choose another file name"):  # fmt: skip
        write_output(out, b"new")
    assert outside.read_text() == "do not touch\n"
    dangling = tmp_path / "magcal.h"
    dangling.symlink_to(tmp_path / "created-by-following.h")
    for exclusive in (False, True):
        with pytest.raises(UserInputError, match="symbolic link"):
            write_output(dangling, b"new", exclusive=exclusive)
    assert not (tmp_path / "created-by-following.h").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["magcal.h", "result.json", "secret.txt"]


def test_write_output_replaces_a_file_atomically_and_exclusive_never_overwrites(
    tmp_path: Path,
) -> None:
    out = tmp_path / "x.csv"
    write_output(out, b"one")
    assert out.read_bytes() == b"one"
    out.chmod(0o640)
    inode = out.stat().st_ino
    write_output(out, b"two")
    assert out.read_bytes() == b"two" and stat.S_IMODE(out.stat().st_mode) == 0o640
    assert out.stat().st_ino != inode  # a new file renamed over the old one, not rewritten
    with pytest.raises(FileExistsError):
        write_output(out, b"three", exclusive=True)
    assert out.read_bytes() == b"two"
    new = tmp_path / "new.yaml"
    write_output(new, b"designed", exclusive=True)
    assert new.read_bytes() == b"designed"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_rig_lab_trend_png_is_not_written_through_a_link(tmp_path: Path) -> None:
    """``rig lab trend --png FILE`` saved the figure by name (matplotlib follows links)."""
    from rig.lab.plot import trend_png
    from rig.lab.queries import Trend

    rows = [{"series": "vector, lot 1", "value": v, "sigma": 0.1, "outlier": False,
             "run_id": f"r{i}"} for i, v in enumerate([1.0, 1.2, 0.9])]  # fmt: skip
    trend = Trend("x0_ut", rows)
    planted = tmp_path / "trend.png"
    planted.symlink_to(tmp_path / "created-through-the-link")
    with pytest.raises(UserInputError, match=r"trend\.png: is a symbolic link"):
        trend_png(trend, planted)
    assert not (tmp_path / "created-through-the-link").exists()
    plain = tmp_path / "plain.png"
    trend_png(trend, plain)
    assert plain.read_bytes().startswith(b"\x89PNG")
