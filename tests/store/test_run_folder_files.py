"""Run-folder files (issue 29): exports and reports never write through a planted link, a linked or
damaged run.sqlite is one line (exit 2), and 'rig verify' covers every file of the folder."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import pytest

from rig.cli import main
from rig.report.acceptance import build_report
from rig.store.seal import MANIFEST_FILE, SEAL_FILE, verify_run
from tests.report.test_acceptance_report import synthetic_run

OUTSIDE = b"a file outside the run folder\n"


@pytest.fixture(scope="module")
def reported_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A closed, sealed run whose reports the rig wrote after the seal (as 'rig run' does)."""
    folder = synthetic_run(tmp_path_factory.mktemp("runs"))
    build_report(folder)
    return folder


@pytest.fixture
def run(reported_run: Path, tmp_path: Path) -> Iterator[Path]:
    """A fresh copy of the reported run, in a runs folder of its own."""
    folder = tmp_path / "runs" / reported_run.name
    shutil.copytree(reported_run, folder)
    yield folder


def _outside(tmp_path: Path, name: str) -> Path:
    path = tmp_path / "outside" / name
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(OUTSIDE)
    return path


def _link(at: Path, target: Path) -> None:
    at.unlink(missing_ok=True)
    at.symlink_to(target)


def test_export_and_report_replace_planted_links_never_their_targets(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    targets = {name: _outside(tmp_path, name) for name in
               ("run.h5", "report.txt", "report.html", "report.pdf", "events.csv")}  # fmt: skip
    for name in ("run.h5", "report.txt", "report.html", "report.pdf"):
        _link(run / name, targets[name])
    (run / "csv").mkdir()
    _link(run / "csv" / "events.csv", targets["events.csv"])
    assert main(["export", str(run), "--format", "hdf5"]) == 0
    assert main(["export", str(run), "--format", "csv"]) == 0
    assert main(["report", str(run)]) == 0
    for name, target in targets.items():
        assert target.read_bytes() == OUTSIDE, name  # the link's target is left alone
    for path in (run / "run.h5", run / "report.txt", run / "report.pdf", run / "csv/events.csv"):
        assert path.is_file() and not path.is_symlink() and path.stat().st_size > 0, path
    assert "VERDICT" in (run / "report.html").read_text()
    # the rig wrote them into the closed run: the manifest knows them, so the folder is intact
    capsys.readouterr()
    assert main(["verify", str(run)]) == 0, capsys.readouterr().out
    assert "INTACT" in capsys.readouterr().out


def test_a_linked_csv_folder_is_refused(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (run / "csv").symlink_to(elsewhere)
    assert main(["export", str(run), "--format", "csv"]) == 2
    err = capsys.readouterr().err.strip()
    assert "is a symbolic link" in err and len(err.splitlines()) == 1, err
    assert list(elsewhere.iterdir()) == []


@pytest.mark.parametrize("command", ["show", "verify", "export", "report"])
def test_a_linked_run_sqlite_or_run_folder_is_one_line(
    run: Path, tmp_path: Path, command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    real = tmp_path / "real.sqlite"
    os.replace(run / "run.sqlite", real)
    (run / "run.sqlite").symlink_to(real)
    before = real.read_bytes()
    assert main([command, str(run)]) == 2
    err = capsys.readouterr().err.strip()
    assert "run.sqlite: is a symbolic link" in err and len(err.splitlines()) == 1, err
    assert real.read_bytes() == before
    # a run folder that is itself a link
    os.replace(real, run / "run.sqlite")
    linked = tmp_path / "linked-run"
    linked.symlink_to(run)
    assert main([command, str(linked)]) == 2
    err = capsys.readouterr().err.strip()
    assert "is a symbolic link" in err and len(err.splitlines()) == 1, err


def _verify(run: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    capsys.readouterr()
    code = main(["verify", str(run), "--quiet"])
    return code, capsys.readouterr().out.splitlines()


def test_an_edited_report_is_a_changed_report_not_changed_data(
    run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _verify(run, capsys)[0] == 0
    html = (run / "report.html").read_text()
    assert "PASS" in html
    (run / "report.html").write_text(html.replace("PASS", "FAIL"))
    code, out = _verify(run, capsys)
    assert code == 1
    assert out[0].endswith("CHANGED (data intact, reports CHANGED, other files intact)"), out
    assert out[1:] == ["  REPORTS  report.html edited since the rig wrote it"], out
    build_report(run)  # the rig rewrites it: intact again
    assert _verify(run, capsys)[0] == 0


def test_deleted_and_added_files_and_tables(run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (run / "report.pdf").unlink()
    (run / "plot.png").write_bytes(b"\x89PNG not from the rig")
    (run / "result.json").write_text('{"verdict": "PASS"}')
    (run / "extra").mkdir()
    (run / "extra" / "notes.txt").write_text("hi")
    (run / "x.png").symlink_to("/etc/passwd")
    code, out = _verify(run, capsys)
    assert code == 1
    assert "data intact, reports CHANGED, other files CHANGED" in out[0], out
    assert "  REPORTS  report.pdf deleted (the rig wrote it)" in out
    for name in ("extra/notes.txt", "plot.png", "result.json"):
        assert f"  FILES    {name} added (the rig did not write it)" in out, out
    assert "  FILES    x.png is a link or not a regular file (added to the folder)" in out
    # a table added to and one dropped from run.sqlite: the data digest cannot see them
    con = sqlite3.connect(run / "run.sqlite")
    con.execute("CREATE TABLE plots (name TEXT)")
    con.execute("DROP INDEX channels_channel_t")
    con.commit()
    con.close()
    code, out = _verify(run, capsys)
    assert "CHANGED (data CHANGED, reports CHANGED, other files CHANGED)" in out[0], out
    assert "  DATA     table plots added to run.sqlite since the run was sealed" in out
    assert (
        "  DATA     index channels_channel_t dropped from run.sqlite since the run was sealed"
        in out
    )


def test_changed_data_and_a_stale_report_are_told_apart(
    run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    con = sqlite3.connect(run / "run.sqlite")
    con.execute("UPDATE results SET value = replace(value, 'PASS', 'FAIL') WHERE name = 'verdict'")
    con.commit()
    con.close()
    code, out = _verify(run, capsys)
    assert code == 1 and "CHANGED (data CHANGED, reports CHANGED, other files intact)" in out[0]
    assert any(line.startswith("  DATA     data changed since the run was sealed") for line in out)
    assert any(line.startswith("  REPORTS  report.txt states data sha256") for line in out)
    # the seal rewritten to match (a run sealed again): the data match, the reports are stale
    from rig.store.seal import seal_run

    seal_run(run)
    code, out = _verify(run, capsys)
    assert code == 1 and "CHANGED (data intact, reports CHANGED, other files intact)" in out[0], out


def test_a_manifest_from_another_seal_is_reported(
    run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    seal = json.loads((run / SEAL_FILE).read_text())
    seal["sealed_at"] = "2020-01-01T00:00:00+00:00"
    (run / SEAL_FILE).write_text(json.dumps(seal))
    code, out = _verify(run, capsys)
    assert code == 1 and "manifest.json does not belong to this seal.json" in "\n".join(out)


def test_a_run_sealed_before_manifests_is_verified_for_its_data(
    run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (run / MANIFEST_FILE).unlink()
    seal = json.loads((run / SEAL_FILE).read_text())
    del seal["schema"]
    (run / SEAL_FILE).write_text(json.dumps(seal))
    (run / "plot.png").write_bytes(b"not checked without a manifest")
    code, out = _verify(run, capsys)
    assert code == 0 and out == [], out
    capsys.readouterr()
    assert main(["verify", str(run)]) == 0
    head = capsys.readouterr().out.splitlines()[0]
    assert "INTACT" in head and "data and sealed copies only: the run has no manifest" in head
    result = verify_run(run)
    assert result.intact and not result.manifest
    # a table the rig never writes is still noticed
    con = sqlite3.connect(run / "run.sqlite")
    con.execute("CREATE TABLE plots (name TEXT)")
    con.commit()
    con.close()
    assert verify_run(run).problems == ["table plots in run.sqlite is not one the rig writes"]
    # rebuilding the report gives the old run a manifest of what its folder holds now
    build_report(run)
    assert (run / MANIFEST_FILE).is_file() and verify_run(run).manifest


def test_a_damaged_run_is_listed_and_never_hides_the_others(
    run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    runs = run.parent
    other = runs / "20000101-000000-other"
    shutil.copytree(run, other)
    size = (run / "run.sqlite").stat().st_size
    with (run / "run.sqlite").open("r+b") as fh:
        fh.truncate(size // 3)
    capsys.readouterr()
    assert main(["runs", "--runs-dir", str(runs)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3, lines
    assert lines[1].startswith(run.name) and " damaged " in lines[1], lines
    assert lines[2].startswith(other.name) and " complete " in lines[2], lines
    for command in ("show", "verify"):
        assert main([command, str(run)]) == 2
        err = capsys.readouterr().err.strip()
        assert "run.sqlite is damaged" in err and len(err.splitlines()) == 1, err


def test_the_manifest_learns_only_files_the_rig_writes_into_a_closed_run(
    run: Path, tmp_path: Path
) -> None:
    from rig.store import new_run
    from rig.store.seal import read_manifest, record_written

    before = read_manifest(run)
    assert before is not None and "report.html" in before["files"]
    outside = _outside(tmp_path, "elsewhere.csv")
    (run / "notes.txt").write_text("an operator's note")  # not the rig's: stays unlisted
    assert record_written(run, [outside, run / "report.html"], "test")
    after = read_manifest(run)
    assert after is not None and set(after["files"]) == set(before["files"])
    assert "notes.txt" not in after["files"] and "elsewhere.csv" not in after["files"]
    live = new_run(tmp_path / "live", "SN-2", procedure="p")  # still running: no seal, no manifest
    (live.folder / "report.txt").write_text("early")
    assert not record_written(live.folder, [live.folder / "report.txt"], "test")
    assert read_manifest(live.folder) is None
    live.close("complete", "done")  # sealing lists what the folder holds
    manifest = read_manifest(live.folder)
    assert manifest is not None and set(manifest["files"]) == {"report.txt"}
