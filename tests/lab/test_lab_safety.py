"""The lab sync against a real PostgreSQL (issue 29): a run changed since it was sealed is refused
and audited, one run the index cannot store never stops the others, a locked table cannot hold a
closing run beyond the documented bound, and no password hides in a percent-encoded URL key."""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psycopg
import pytest

from bench.labfixture import generate_runs
from rig.errors import UserInputError
from rig.lab.schema import LabUnavailableError
from rig.lab.sync import run_folders, sync_runs
from rig.lab.url import config_url, has_password, masked
from rig.store import new_run

pytestmark = pytest.mark.services


def rig_lab(*args: str, url: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rig.cli", "lab", *args, "--lab", url],
                          capture_output=True, text=True, timeout=120)  # fmt: skip


def rows(url: str, sql: str) -> list[tuple[Any, ...]]:
    with psycopg.connect(url) as conn:
        return list(conn.execute(sql).fetchall())  # type: ignore[arg-type,unused-ignore]


def test_a_run_changed_after_its_seal_is_refused_and_audited(lab_url: str, tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    folders = generate_runs(runs, 3, rig="cage-1", seed=11)
    forged = folders[1]
    con = sqlite3.connect(forged / "run.sqlite")  # the verdict forged in an unsynced run
    con.execute("UPDATE results SET value = ? WHERE name = 'verdict'",
                (json.dumps({"overall": "PASS", "criteria": []}),))  # fmt: skip
    con.commit()
    con.close()
    proc = rig_lab("sync", "--runs-dir", str(runs), "--json", url=lab_url)
    assert proc.returncode == 1, proc.stderr
    assert json.loads(proc.stdout) | {"added": 2, "refused": 1, "not_stored": 0} == json.loads(
        proc.stdout
    )
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"rig: WARNING: run {forged.name}: its data"
                                                   " changed since the run was sealed"), lines  # fmt: skip
    indexed = {r[0] for r in rows(lab_url, "SELECT run_id FROM lab_runs")}
    assert indexed == {folders[0].name, folders[2].name}  # the forged verdict never got in
    # the audit shows it, and a second sync counts a second attempt
    assert rig_lab("sync", "--runs-dir", str(runs), url=lab_url).returncode == 1
    audit = json.loads(rig_lab("audit", "--json", url=lab_url).stdout)
    (row,) = audit["refused"]
    assert row["run_id"] == forged.name and row["kind"] == "changed since sealed"
    assert row["attempts"] == 2 and "data changed since the run was sealed" in row["reason"]
    assert forged.name in rig_lab("audit", url=lab_url).stdout
    # a table added to run.sqlite or a changed configuration copy is refused as well
    more = generate_runs(tmp_path / "more", 2, rig="cage-1", seed=12)
    con = sqlite3.connect(more[0] / "run.sqlite")
    con.execute("CREATE TABLE plots (name TEXT)")
    con.commit()
    con.close()
    (more[1] / "rig.toml").write_text("[lab]\nrig = 'cage-9'\n")
    report = sync_runs(lab_url, run_folders(tmp_path / "more"))
    assert report.added == [] and len(report.refused) == 2, report
    why = {line.split(":", 1)[0]: line for line in report.refused}
    assert "table plots added to run.sqlite" in why[more[0].name]
    assert "rig.toml changed since the run was sealed" in why[more[1].name]


def test_one_run_the_index_cannot_store_never_stops_the_others(
    lab_url: str, tmp_path: Path
) -> None:
    runs = tmp_path / "runs"
    generate_runs(runs, 2, rig="cage-1", seed=13)
    w = new_run(runs, "nul", procedure="DUT\x00acceptance", dut_serial="SN-\x000042",
                operator="ana", parameters={"dut_serial": "SN-\x000042"})  # fmt: skip
    w.close("complete", "recorded before control characters were refused")
    proc = rig_lab("sync", "--runs-dir", str(runs), "--json", url=lab_url)
    assert proc.returncode == 1, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["added"] == 2 and summary["not_stored"] == 1, summary
    lines = proc.stderr.strip().splitlines()
    assert (
        len(lines) == 1 and f"cannot store run {w.folder.name}: PostgreSQL text fields" in lines[0]
    )
    # every later sync goes on: a new run is added, the bad one reported again, nothing else
    generate_runs(runs, 1, rig="cage-1", seed=14)
    again = rig_lab("sync", "--runs-dir", str(runs), "--json", url=lab_url)
    assert json.loads(again.stdout) | {"added": 1, "already_indexed": 2, "not_stored": 1} == (
        json.loads(again.stdout)
    ), again.stdout
    (row,) = json.loads(rig_lab("audit", "--json", url=lab_url).stdout)["refused"]
    assert row["kind"] == "cannot be stored" and row["attempts"] == 2
    assert row["run_id"] == w.folder.name


def test_a_locked_index_table_holds_a_closing_run_at_most_the_bound(
    lab_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    from rig.engine.runner import LAB_TIMEOUT_S
    from tests.simrun import TINY_PROCEDURE, run_on_sim

    generate_runs(tmp_path / "first", 1, rig="cage-1", seed=15)
    assert len(sync_runs(lab_url, run_folders(tmp_path / "first")).added) == 1  # schema exists
    holder = psycopg.connect(lab_url)
    try:
        # held until rollback, at most 30 s: a sync that waits for it fails the timing, never hangs
        holder.execute("SET idle_in_transaction_session_timeout = '30s'")
        holder.execute("LOCK TABLE lab_runs IN ACCESS EXCLUSIVE MODE")
        # the sync alone: refused within the bound, one line naming the lock
        (later,) = generate_runs(tmp_path / "later", 1, rig="cage-1", seed=16)
        t0 = time.monotonic()
        with pytest.raises(LabUnavailableError, match="lock timeout") as err:
            sync_runs(lab_url, [later], timeout_s=LAB_TIMEOUT_S)
        took = time.monotonic() - t0
        assert 0.8 * LAB_TIMEOUT_S < took < LAB_TIMEOUT_S + 1.5, took
        assert "\n" not in str(err.value)
        # a whole run with the index configured: it exits within the bound after it closed
        monkeypatch.setenv("RIG_LAB_URL", lab_url)
        capfd.readouterr()
        outcome = run_on_sim(tmp_path, TINY_PROCEDURE)
        after_close = time.time() - (outcome.folder / "seal.json").stat().st_mtime
    finally:
        with contextlib.suppress(psycopg.Error):
            holder.rollback()
        holder.close()
    assert outcome.status == "complete", outcome.reason
    assert after_close < LAB_TIMEOUT_S + 1.5, after_close
    err_text = capfd.readouterr().err
    assert "the run was not added to the lab index" in err_text and "lock timeout" in err_text
    print(f"sync alone {took:.2f} s; run exit {after_close:.2f} s after its seal (locked table)")
    # with the lock gone, the next sync adds both
    assert len(sync_runs(lab_url, [later, outcome.folder]).added) == 2


def test_a_linked_run_sqlite_is_one_line_and_the_others_sync(lab_url: str, tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    folders = generate_runs(runs, 3, rig="cage-1", seed=17)
    real = tmp_path / "elsewhere.sqlite"
    os.replace(folders[1] / "run.sqlite", real)
    (folders[1] / "run.sqlite").symlink_to(real)
    before = real.read_bytes()
    proc = rig_lab("sync", "--runs-dir", str(runs), "--json", url=lab_url)
    assert proc.returncode == 0 and json.loads(proc.stdout)["added"] == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"cannot read run {folders[1].name}" in lines[0], lines
    assert "run.sqlite: is a symbolic link" in lines[0]
    assert real.read_bytes() == before


@pytest.mark.parametrize("key", ["pass%77ord", "%70assword", "PASS%57ORD", "%70%61%73%73word"])
def test_a_percent_encoded_password_key_is_refused(key: str, tmp_path: Path) -> None:
    url = f"postgresql://rig@labdb/lab?sslmode=require&{key}=s3cret"
    assert has_password(url) and "s3cret" not in masked(url)
    with pytest.raises(UserInputError, match="holds a password"):
        config_url({"lab": {"url": url}}, "rig.toml")
    cfg = tmp_path / "rig.toml"
    cfg.write_text(f'[lab]\nurl = "{url}"\n', encoding="utf-8")
    proc = subprocess.run([sys.executable, "-m", "rig.cli", "lab", "runs", "--rig", str(cfg)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 2 and "holds a password" in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "s3cret" not in proc.stderr
    assert not has_password("postgresql://rig@labdb/lab?sslmode=verify-full&passfile=x")
