"""Forged runs and extreme values against the lab index (issue 51), on the real PostgreSQL of
tests/lab/conftest.py.

The attack: a runs folder another account can write; that account makes a run from nothing with
the rig's own store API (PASS, an invented serial), edits a run and seals it again, leaves an
unsealed one; the owner's own ``rig lab sync`` pushed all three. The other account is played by
``os.chown`` to an unused uid (these tests run as root; skipped otherwise). A value of 1e308
moved a lot's control limits to ~1e307 and made ``rig lab audit`` crash.
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
import subprocess
import sys
from pathlib import Path
from typing import Any

import psycopg
import pytest

from bench.labfixture import generate_runs
from rig.lab.sync import run_folders, sync_runs
from rig.store import new_run
from rig.store.seal import seal_run, verify_run

pytestmark = pytest.mark.services

OTHER_UID = 54321
"""An account that is not the rig's (no such user needed: only the number is stored)."""


def rig_lab(*args: str, url: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rig.cli", "lab", *args, "--lab", url],
                          capture_output=True, text=True, timeout=120)  # fmt: skip


def rows(url: str, sql: str) -> list[tuple[Any, ...]]:
    with psycopg.connect(url) as conn:
        return list(conn.execute(sql).fetchall())  # type: ignore[arg-type,unused-ignore]


def as_other_account(path: Path) -> None:
    """``path`` and everything under it owned by OTHER_UID, as if that account had written it."""
    for root, dirs, files in os.walk(path):
        for name in [*dirs, *files]:
            os.chown(Path(root) / name, OTHER_UID, OTHER_UID, follow_symlinks=False)
    os.chown(path, OTHER_UID, OTHER_UID, follow_symlinks=False)


def from_nothing(runs: Path, serial: str) -> Path:
    """A sealed PASS run of an invented serial, made with the rig's own store API."""
    w = new_run(runs, serial, procedure="DUT acceptance", dut_serial=serial, operator="ana",
                parameters={"dut_serial": serial, "lot": "1"})  # fmt: skip
    w.set_result("verdict", {"overall": "PASS", "criteria": []})
    w.close("complete", "all steps done")
    return w.folder


@pytest.fixture
def root_only() -> None:
    if os.geteuid() != 0:
        pytest.skip("playing another account needs root (os.chown)")


@pytest.mark.usefixtures("root_only")
def test_forged_runs_from_another_account_never_reach_the_index(
    lab_url: str, tmp_path: Path
) -> None:
    runs = tmp_path / "runs"
    old = os.umask(0)  # a shared runs folder: everything made in it writable by everyone
    try:
        honest = generate_runs(runs, 3, rig="cage-1", seed=21)
    finally:
        os.umask(old)
    assert runs.stat().st_mode & 0o777 == 0o777
    # the other account: a run from nothing, an edited run sealed again, an unsealed run
    forged = from_nothing(runs, "SN-9999")
    as_other_account(forged)
    edited = honest[1]
    con = sqlite3.connect(edited / "run.sqlite")
    con.execute("UPDATE results SET value = ? WHERE name = 'verdict'",
                (json.dumps({"overall": "PASS", "criteria": []}),))  # fmt: skip
    con.commit()
    con.close()
    seal_run(edited)
    for name in ("seal.json", "manifest.json"):
        os.chown(edited / name, OTHER_UID, OTHER_UID)
    # the seals verify (the generated report.txt states no digest: a reports matter only)
    assert verify_run(forged).intact and set(verify_run(edited).changed) == {"reports"}
    unsealed = from_nothing(runs, "SN-9998")
    (unsealed / "seal.json").unlink()
    (unsealed / "manifest.json").unlink()
    as_other_account(unsealed)

    # the runs folder another account can write: refused whole, before anything is read
    proc = rig_lab("sync", "--runs-dir", str(runs), url=lab_url)
    assert proc.returncode == 2 and proc.stdout == "", proc
    assert proc.stderr.strip() == (
        f"rig: error: runs folder {runs} can be written by group and other (mode 777): anyone"
        f" there can forge a sealed run; chmod go-w {runs}; nothing was pushed"
    ), proc.stderr
    assert rows(lab_url, "SELECT to_regclass('lab_runs') IS NULL") == [(True,)]  # not even opened

    # the lab's fix for the runs folder; each exposed run is still skipped, one line each
    runs.chmod(0o755)
    proc = rig_lab("sync", "--runs-dir", str(runs), "--json", url=lab_url)
    assert proc.returncode == 1, proc.stderr
    assert json.loads(proc.stdout)["added"] == 0 and json.loads(proc.stdout)["skipped"] == 5
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 5, lines
    said = {line.removeprefix("rig: WARNING: run ").split(":", 1)[0]: line for line in lines}
    for folder in honest:
        assert f"run folder {folder} can be written by group and other (mode 777)" in (
            said[folder.name]
        ) and said[folder.name].endswith(f"chmod go-w {folder}; skipped"), said[folder.name]
    for folder in (forged, unsealed):
        assert (
            f"run folder {folder} is owned by uid {OTHER_UID}, not by this account"
            in (said[folder.name])
        ), said[folder.name]
    assert rows(lab_url, "SELECT count(*) FROM lab_runs") == [(0,)]

    # the rig's own runs, made private: pushed; the edited one still not (its seal is the other
    # account's); the forged ones never
    for folder in honest:
        folder.chmod(0o755)
        for entry in folder.iterdir():
            entry.chmod(entry.stat().st_mode & ~0o022)
    report = sync_runs(lab_url, run_folders(runs))
    assert sorted(report.added) == sorted([honest[0].name, honest[2].name]), report
    why = {line.split(":", 1)[0]: line for line in report.skipped}
    assert set(why) == {edited.name, forged.name, unsealed.name}, report.skipped
    assert f"run file {edited / 'manifest.json'} is owned by uid {OTHER_UID}" in why[edited.name]
    indexed = {r[0] for r in rows(lab_url, "SELECT dut_serial FROM lab_runs")}
    assert "SN-9999" not in indexed and "SN-9998" not in indexed


def test_an_unsealed_run_of_the_rig_s_own_is_skipped_with_a_line(
    lab_url: str, tmp_path: Path
) -> None:
    runs = tmp_path / "runs"
    folders = generate_runs(runs, 2, rig="cage-1", seed=22)
    (folders[0] / "seal.json").unlink()
    proc = rig_lab("sync", "--runs-dir", str(runs), "--json", url=lab_url)
    assert proc.returncode == 1, proc.stderr
    assert json.loads(proc.stdout) | {"added": 1, "skipped": 1} == json.loads(proc.stdout)
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith(f"rig: WARNING: run {folders[0].name}: not sealed, so its data cannot"
                           " be checked") and line.endswith("; skipped"), line  # fmt: skip
    assert [r[0] for r in rows(lab_url, "SELECT run_id FROM lab_runs")] == [folders[1].name]
    (row,) = json.loads(rig_lab("audit", "--json", url=lab_url).stdout)["refused"]
    assert row["run_id"] == folders[0].name and row["kind"] == "not sealed"


@pytest.mark.parametrize(
    ("where", "value", "said"),
    [
        ("offset", 1e308, "calibrate x0_ut = 1e+308 is outside -100000 .. 100000"),
        ("offset", -1e6, "calibrate x0_ut = -1000000.0 is outside -100000 .. 100000"),
        ("sigma", 1e308, "calibrate x0_ut sigma = 1e+308 is outside 0 .. 200000"),
        ("scale", -1.0, "calibrate a = -1.0 is outside 0.001 .. 1000"),
        ("criterion", 1e308, "criterion 'x offset' value = 1e+308 uT is outside -100000 .."),
        ("criterion", 10**400, "criterion 'x offset' value = inf uT is outside"),
    ],
)
def test_a_value_beyond_its_physical_range_refuses_the_run(
    lab_url: str, tmp_path: Path, where: str, value: float, said: str
) -> None:
    runs = tmp_path / "runs"
    folders = generate_runs(runs, 2, rig="cage-1", seed=23)
    bad = folders[0]
    con = sqlite3.connect(bad / "run.sqlite")
    if where == "criterion":
        (text,) = con.execute("SELECT value FROM results WHERE name = 'verdict'").fetchone()
        verdict = json.loads(text)
        verdict["criteria"][1]["value"] = value
        con.execute("UPDATE results SET value = ? WHERE name = 'verdict'", (json.dumps(verdict),))
    else:
        (text,) = con.execute("SELECT value FROM results WHERE name = 'calibrate'").fetchone()
        cal = json.loads(text)
        block = cal["sigma"]["springmann"] if where == "sigma" else cal["springmann"]
        block["a" if where == "scale" else "x0_ut"] = value
        con.execute("UPDATE results SET value = ? WHERE name = 'calibrate'", (json.dumps(cal),))
    con.commit()
    con.close()
    seal_run(bad)  # the rig's own account sealed it: only the range stands in the way
    proc = rig_lab("sync", "--runs-dir", str(runs), "--json", url=lab_url)
    assert proc.returncode == 1, proc.stderr
    assert json.loads(proc.stdout) | {"added": 1, "refused": 1} == json.loads(proc.stdout)
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith(f"rig: WARNING: run {bad.name}: {said}"), line
    assert [r[0] for r in rows(lab_url, "SELECT run_id FROM lab_runs")] == [folders[1].name]
    (row,) = json.loads(rig_lab("audit", "--json", url=lab_url).stdout)["refused"]
    assert row["kind"] == "value out of range" and said in row["reason"]


@pytest.mark.parametrize("extreme", ["1e308", "-1e308", "Infinity", "NaN"])
def test_audit_and_trend_survive_an_extreme_value_an_older_sync_stored(
    lab_url: str, tmp_path: Path, extreme: str
) -> None:
    runs = tmp_path / "runs"
    generate_runs(runs, 40, rig="cage-1", seed=24, lots=1)
    assert sync_runs(lab_url, run_folders(runs)).added
    with psycopg.connect(lab_url) as conn:  # as a sync before values were bounded stored it
        conn.execute(
            "UPDATE lab_results SET value = %s::float8 WHERE name = 'x0_ut'"
            " AND run = (SELECT min(id) FROM lab_runs)",
            (extreme,),
        )
    audit = rig_lab("audit", "--json", url=lab_url)
    assert audit.returncode == 0, audit.stderr
    (rig,) = json.loads(audit.stdout)["rigs"]
    assert rig["rig"] == "cage-1" and rig["outliers"] >= 1, rig
    assert rig_lab("audit", url=lab_url).returncode == 0
    trend = rig_lab("trend", "x0_ut", "--json", "--png", str(tmp_path / "t.png"), url=lab_url)
    assert trend.returncode == 0, trend.stderr
    found = json.loads(trend.stdout)
    (limits,) = found["limits"]
    assert limits["n"] == 39  # the extreme value is no part of the limits
    assert 1.0 < limits["lcl"] < limits["mean"] < limits["ucl"] < 2.5, limits
    (flagged,) = [r for r in found["rows"] if not r["in_range"]]
    assert flagged["outlier"] and (math.isnan(flagged["value"]) or abs(flagged["value"]) > 1e300)
    assert (tmp_path / "t.png").stat().st_size > 0
