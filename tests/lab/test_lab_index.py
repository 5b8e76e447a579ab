"""The lab index against a real PostgreSQL server (tests/lab/conftest.py): concurrent syncs, a
killed sync resumed, re-sync, a database that is down, credentials, and the queries' answers."""

from __future__ import annotations

import json
import os
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import psycopg
import pytest

from bench.labfixture import PASSWORD, PgServer, _free_port, generate_runs
from rig.errors import UserInputError
from rig.lab.schema import HEAD
from rig.lab.sync import run_folders, sync_runs
from rig.lab.url import config_url, masked
from rig.store import new_run

pytestmark = pytest.mark.services

RIGS = ("cage-1", "cage-2", "cage-3", "cage-4")
PER_RIG = 250


def rig_lab(
    *args: str, url: str | None = None, timeout: float = 120
) -> subprocess.CompletedProcess[str]:
    """``rig lab ...`` as its own process."""
    argv = [sys.executable, "-m", "rig.cli", "lab", *args, *(["--lab", url] if url else [])]
    return subprocess.run(argv, capture_output=True, text=True, timeout=timeout)


def scalar(url: str, sql: str) -> Any:
    with psycopg.connect(url) as conn:
        row = conn.execute(sql).fetchone()  # type: ignore[arg-type]
    return row[0] if row else None


def fresh_db(pg: PgServer, name: str) -> str:
    pg.psql(f"CREATE DATABASE {name} OWNER rig", db="postgres")
    return pg.url.rsplit("/", 1)[0] + f"/{name}"


@pytest.fixture(scope="module")
def rig_dirs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Four rigs' runs folders of 250 sealed runs each (cage-3 has an offset outlier every 25th)."""
    dirs = []
    for k, rig in enumerate(RIGS):
        d = tmp_path_factory.mktemp(rig)
        generate_runs(d, PER_RIG, rig=rig, seed=k, outlier_every=25 if rig == "cage-3" else 0)
        dirs.append(d)
    return dirs


@pytest.fixture(scope="module")
def synced(pg: PgServer, rig_dirs: list[Path]) -> Iterator[str]:
    """Four ``rig lab sync`` processes at once, one per rig, into an empty database; its URL."""
    os.environ["PGPASSWORD"] = PASSWORD  # module scope: the autouse fixture is function scoped
    url = fresh_db(pg, f"lab_four_{os.getpid()}")
    procs = [
        subprocess.Popen([sys.executable, "-m", "rig.cli", "lab", "sync", "--runs-dir", str(d),
                          "--lab", url], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for d in rig_dirs
    ]  # fmt: skip
    outs = [p.communicate(timeout=180) for p in procs]
    for p, (out, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err
        assert out.startswith(f"{PER_RIG} runs added"), out
    yield url


def test_four_concurrent_syncs_index_every_run_once(synced: str, rig_dirs: list[Path]) -> None:
    assert scalar(synced, "SELECT count(*) FROM lab_runs") == 4 * PER_RIG
    assert scalar(synced, "SELECT count(DISTINCT run_uid) FROM lab_runs") == 4 * PER_RIG
    assert scalar(synced, "SELECT count(DISTINCT (rig, run_id)) FROM lab_runs") == 4 * PER_RIG
    assert scalar(synced, "SELECT version_num FROM alembic_version") == HEAD  # migrated once
    with psycopg.connect(synced) as conn:
        indexed = set(conn.execute("SELECT rig, run_id FROM lab_runs").fetchall())
    assert indexed == {(rig, f.name) for rig, d in zip(RIGS, rig_dirs, strict=True)
                       for f in run_folders(d)}  # fmt: skip
    # each run whole: its instruments, criteria and results came with it
    assert scalar(synced, "SELECT count(*) FROM lab_instruments") == 2 * 4 * PER_RIG
    assert scalar(synced, "SELECT count(*) FROM lab_criteria") == 2 * 4 * PER_RIG
    assert scalar(synced, "SELECT count(*) FROM lab_results") == 5 * 4 * PER_RIG


def test_resync_adds_nothing(synced: str, rig_dirs: list[Path]) -> None:
    proc = rig_lab("sync", "--runs-dir", str(rig_dirs[1]), "--json", url=synced)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == {"added": 0, "already_indexed": PER_RIG,
                                       "still_running": 0, "unreadable": 0, "refused": 0,
                                       "not_stored": 0, "skipped": 0}  # fmt: skip
    assert scalar(synced, "SELECT count(*) FROM lab_runs") == 4 * PER_RIG


def test_killed_sync_is_completed_by_the_next(pg: PgServer, rig_dirs: list[Path]) -> None:
    url = fresh_db(pg, f"lab_killed_{os.getpid()}")
    assert rig_lab("runs", url=url).returncode == 0  # the schema exists before the count polls
    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", "lab", "sync", "--runs-dir",
                             str(rig_dirs[0]), "--lab", url], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)  # fmt: skip
    with psycopg.connect(url, autocommit=True) as conn:
        deadline = time.monotonic() + 60
        while (n := conn.execute("SELECT count(*) FROM lab_runs").fetchone()[0]) < 5:  # type: ignore[index]
            assert time.monotonic() < deadline and proc.poll() is None, "the sync never started"
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        # a COMMIT the server had received when the client died still lands: count once the
        # server has finished the killed connection (its backend gone), not when the client has
        while conn.execute(
            "SELECT count(*) FROM pg_stat_activity WHERE datname = current_database()"
            " AND pid <> pg_backend_pid() AND backend_type = 'client backend'"
        ).fetchone()[0]:  # type: ignore[index]  # fmt: skip
            assert time.monotonic() < deadline + 60, "the killed sync's connection never ended"
            time.sleep(0.01)
        n = conn.execute("SELECT count(*) FROM lab_runs").fetchone()[0]  # type: ignore[index]
        assert 5 <= n < PER_RIG, n
        # whole runs only: no run row without its criteria and results
        partial = conn.execute(
            "SELECT count(*) FROM lab_runs r WHERE (SELECT count(*) FROM lab_criteria c"
            " WHERE c.run = r.id) <> 2 OR (SELECT count(*) FROM lab_results s WHERE s.run = r.id) <> 5"
        ).fetchone()[0]  # type: ignore[index]  # fmt: skip
        assert partial == 0
    again = rig_lab("sync", "--runs-dir", str(rig_dirs[0]), "--json", url=url)
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout)["added"] == PER_RIG - n
    assert scalar(url, "SELECT count(*) FROM lab_runs") == PER_RIG


def test_queries_answer_from_the_index(synced: str, rig_dirs: list[Path], tmp_path: Path) -> None:
    from rig.store import RunReader

    # every acceptance of one serial, across the four rigs
    want = []
    for d in rig_dirs:
        for f in run_folders(d):
            r = RunReader(f)
            if r.meta().get("dut_serial") == "SN-0007":
                want.append(f.name)
            r.close()
    proc = rig_lab("dut", "SN-0007", "--json", url=synced)
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(proc.stdout)
    assert sorted(r["run_id"] for r in rows) == sorted(want) and want
    assert {r["rig"] for r in rows} <= set(RIGS)

    runs = json.loads(
        rig_lab("runs", "--dut", "SN-0007", "--limit", "3", "--json", url=synced).stdout
    )
    assert len(runs) == 3 and {r["dut_serial"] for r in runs} == {"SN-0007"}
    table = rig_lab("runs", "--status", "failed", url=synced).stdout.splitlines()
    assert table[0].split()[:3] == ["RUN_ID", "RIG", "STARTED_AT"] and len(table) > 1
    assert all(" failed " in line for line in table[1:])

    # the trend of a lot: control limits from the lot's spread, cage-3's offsets outside them
    png = tmp_path / "x0.png"
    proc = rig_lab("trend", "x0_ut", "--lot", "2", "--png", str(png), "--json", url=synced)
    assert proc.returncode == 0, proc.stderr
    trend = json.loads(proc.stdout)
    values = [r["value"] for r in trend["rows"]]
    assert {r["lot"] for r in trend["rows"]} == {"2"} and len(values) > 50
    (lim,) = trend["limits"]
    mean, sd = statistics.fmean(values), statistics.stdev(values)
    assert lim["mean"] == pytest.approx(mean) and lim["ucl"] == pytest.approx(mean + 3 * sd)
    outliers = [r for r in trend["rows"] if r["outlier"]]
    assert outliers and {r["rig"] for r in outliers} == {"cage-3"}
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # the audit: every 10th run of each rig used an expired reference certificate
    proc = rig_lab("audit", "--json", url=synced)
    assert proc.returncode == 0, proc.stderr
    audit = json.loads(proc.stdout)
    assert len(audit["expired_certificates"]) == 4 * PER_RIG // 10
    assert {r["certificate_expires"] for r in audit["expired_certificates"]} == {"2020-06-30"}
    assert audit["unsealed"] == []
    worst, *others = audit["rigs"]  # ordered by the fraction of values outside control limits
    assert worst["rig"] == "cage-3" and worst["outliers"] >= 10, audit["rigs"]
    assert all(worst["outliers"] > 3 * r["outliers"] for r in others), audit["rigs"]
    text = rig_lab("audit", url=synced).stdout
    assert "runs with an expired instrument certificate:" in text and "FGM-10" in text


def test_unsealed_and_running_runs(lab_url: str, tmp_path: Path) -> None:
    """A closed run without a seal is skipped (the audit lists it as refused, issue 51); a run
    still being recorded is left for a later sync."""
    folders = generate_runs(tmp_path, 3, rig="cage-9", seed=9)
    (folders[1] / "seal.json").unlink()
    running = new_run(tmp_path, "still-running", procedure="smoke")
    try:
        report = sync_runs(lab_url, run_folders(tmp_path))
    finally:
        running.close("complete", "done")
    assert len(report.added) == 2 and report.running == [running.folder.name]
    assert [line.split(":", 1)[0] for line in report.skipped] == [folders[1].name]
    proc = rig_lab("audit", "--json", url=lab_url)
    assert json.loads(proc.stdout)["unsealed"] == []
    assert [r["run_id"] for r in json.loads(proc.stdout)["refused"]] == [folders[1].name]
    assert len(sync_runs(lab_url, run_folders(tmp_path)).added) == 1  # now closed and sealed


def test_database_down_is_one_line_and_exit_2(tmp_path: Path) -> None:
    generate_runs(tmp_path, 2, rig="cage-1", seed=3)
    url = f"postgresql://rig:{PASSWORD}@127.0.0.1:{_free_port()}/lab"
    proc = rig_lab("sync", "--runs-dir", str(tmp_path), url=url)
    assert proc.returncode == 2 and proc.stdout == ""
    (line,) = proc.stderr.splitlines()
    assert "not available" in line and "rig lab sync" in line and "127.0.0.1" in line
    assert PASSWORD not in proc.stderr and "rig:***@" in line
    assert len(run_folders(tmp_path)) == 2  # nothing lost: the folders are the source


def test_credentials_never_printed_nor_stored(lab_url: str, pg: PgServer, tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    generate_runs(runs, 3, rig="cage-1", seed=4)
    with_pw = lab_url.replace("rig@", f"rig:{PASSWORD}@")
    env = {k: v for k, v in os.environ.items() if k != "PGPASSWORD"}
    proc = subprocess.run([sys.executable, "-m", "rig.cli", "lab", "sync", "--runs-dir", str(runs),
                           "--lab", with_pw], capture_output=True, text=True, env=env)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert PASSWORD not in proc.stdout + proc.stderr and "rig:***@127.0.0.1" in proc.stdout
    # a wrong password: refused, one line, no password shown
    bad = rig_lab("runs", url=lab_url.replace("rig@", "rig:wrong-pw-123@"))
    assert bad.returncode == 2 and "wrong-pw-123" not in bad.stderr, bad.stderr
    assert "password authentication failed" in bad.stderr
    for path in runs.rglob("*"):
        if path.is_file():
            assert PASSWORD.encode() not in path.read_bytes(), path
    # a rig configuration is copied into each run folder: it may not hold a password
    cfg = tmp_path / "rig.toml"
    cfg.write_text(f'[lab]\nurl = "{with_pw}"\n', encoding="utf-8")
    proc = rig_lab("runs", "--rig", str(cfg))
    assert proc.returncode == 2 and "holds a password" in proc.stderr
    assert PASSWORD not in proc.stderr
    with pytest.raises(UserInputError, match="holds a password"):
        config_url({"lab": {"url": with_pw}}, cfg)
    assert masked(with_pw) == lab_url.replace("rig@", "rig:***@")


def test_url_from_the_configuration_and_the_environment(lab_url: str, tmp_path: Path) -> None:
    generate_runs(tmp_path / "runs", 1, rig="cage-1", seed=5)
    cfg = tmp_path / "rig.toml"
    cfg.write_text(f'[lab]\nurl = "{lab_url}"\nrig = "cage-1"\n', encoding="utf-8")
    proc = rig_lab("sync", "--runs-dir", str(tmp_path / "runs"), "--rig", str(cfg))
    assert proc.returncode == 0 and proc.stdout.startswith("1 runs added"), proc.stderr
    env = dict(os.environ, RIG_LAB_URL=lab_url)
    proc = subprocess.run([sys.executable, "-m", "rig.cli", "lab", "runs", "--json"],
                          capture_output=True, text=True, env=env)  # fmt: skip
    assert proc.returncode == 0 and len(json.loads(proc.stdout)) == 1
    none = subprocess.run([sys.executable, "-m", "rig.cli", "lab", "runs"], capture_output=True,
                          text=True, env={k: v for k, v in env.items() if k != "RIG_LAB_URL"})  # fmt: skip
    assert none.returncode == 2 and "no lab index configured" in none.stderr


def test_run_close_syncs_best_effort(
    lab_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The runner's close path: the run lands in the index; an index that is down is one warning
    and no exception (the run itself is never failed by it)."""
    from rig.engine.runner import Runner

    (folder,) = generate_runs(tmp_path, 1, rig="cage-1", seed=6)
    me = SimpleNamespace(quiet=False)
    Runner._sync_lab(me, lab_url, folder)  # type: ignore[arg-type]
    assert scalar(lab_url, "SELECT count(*) FROM lab_runs") == 1
    down = f"postgresql://rig:{PASSWORD}@127.0.0.1:{_free_port()}/lab"
    Runner._sync_lab(me, down, folder)  # type: ignore[arg-type]
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("rig: run added to the lab index")
    assert err[1].startswith("rig: WARNING: the run was not added") and PASSWORD not in err[1]
    assert len(err) == 2


def test_lab_help_and_no_heavy_import() -> None:
    """Every ``rig lab`` argument has help; building the parser (every ``rig`` call) and the
    runner import no database or plotting module: they load when the index is used."""
    from rig.cli import build_parser

    parser = build_parser()
    lab = next(a for a in parser._actions if a.dest == "command").choices["lab"]  # type: ignore[index]
    subs = next(a for a in lab._actions if a.dest == "lab_command").choices
    assert set(subs) == {"sync", "runs", "dut", "trend", "audit"}
    for name, sub in subs.items():
        for action in sub._actions:
            assert action.help, f"rig lab {name} {action.dest} has no help"
    code = (
        "import sys; from rig.cli import build_parser; build_parser().parse_args(['lab', 'runs']);"
        " import rig.engine.runner;"
        " sys.exit(sorted(m for m in sys.modules if m.split('.')[0] in"
        " ('psycopg', 'sqlalchemy', 'alembic', 'matplotlib')) or 0)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_a_run_on_the_simulator_lands_in_the_index_at_close(
    lab_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from tests.simrun import TINY_PROCEDURE, run_on_sim

    monkeypatch.setenv("RIG_LAB_URL", lab_url)
    outcome = run_on_sim(tmp_path, TINY_PROCEDURE)
    assert outcome.status == "complete", outcome.reason
    with psycopg.connect(lab_url) as conn:
        run = conn.execute("SELECT run_id, dut_serial, lot, status, verdict, data_sha256, host"
                           " FROM lab_runs").fetchall()  # fmt: skip
        crit = conn.execute("SELECT name, unit, max, margin, verdict FROM lab_criteria").fetchall()
        inst = conn.execute("SELECT name FROM lab_instruments ORDER BY name").fetchall()
    ((run_id, dut, lot, status, verdict, sha, host),) = run
    seal = json.loads((outcome.folder / "seal.json").read_text())
    assert (run_id, dut, lot, status, verdict) == (
        outcome.folder.name,
        "SN-0042",
        "7",
        "complete",
        "PASS",
    )
    assert sha == seal["data_sha256"] and host
    ((name, unit, hi, margin, v),) = crit
    assert unit == "nT"
    assert name == "DUT noise at null field" and hi == 200 and 0 < margin <= 200 and v == "PASS"
    assert ("reference",) in inst and ("dut",) in inst


def test_a_password_in_the_rig_configuration_refuses_the_run(tmp_path: Path) -> None:
    """Refused before a run folder (with its copy of the configuration) exists."""
    from rig.engine.runner import Runner

    cfg = SimpleNamespace(raw={"lab": {"url": f"postgresql://rig:{PASSWORD}@db/lab"}},
                          path=tmp_path / "rig.toml")  # fmt: skip
    runner = Runner(SimpleNamespace(parameters={}), cfg, tmp_path / "runs")  # type: ignore[arg-type]
    with pytest.raises(UserInputError, match="holds a password") as err:
        runner.run()
    assert PASSWORD not in str(err.value)
    assert not (tmp_path / "runs").exists()


def test_the_same_views_on_the_rig_serve_page(synced: str, rig_dirs: list[Path]) -> None:
    """`rig serve --lab URL` shows runs, a DUT's acceptances, a trend with its plot and the audit,
    in Debian's chromium; without the index the Lab page says how to configure it."""
    from playwright.sync_api import sync_playwright

    from rig.child_process import stop_child
    from tests.web.conftest import (
        CHROMIUM_ARGS,
        chromium_path,
        owner_client,
        screenshot,
        serve_process,
        split_token,
        wait_js,
    )

    server, url = serve_process(rig_dirs[0], "--lab", synced)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.goto(url)
            page.click("nav >> text=Lab")
            assert page.inner_text("#lab-title") == "Lab index: runs of every rig"
            rows = page.locator("table.lab tbody tr")
            assert rows.count() == 100  # the page's default limit, newest first, every rig
            page.fill("input[name=dut]", "SN-0007")
            page.click("text=Show runs")
            serials = page.locator("table.lab tbody td:nth-child(5)").all_inner_texts()
            assert serials and set(serials) == {"SN-0007"}
            page.locator("table.lab tbody a", has_text="SN-0007").first.click()
            assert page.inner_text("#lab-title") == "Every run of DUT SN-0007"
            assert page.locator("table.lab tbody tr").count() == len(serials)
            page.goto(f"{split_token(url)[0]}/lab/trend?param=x0_ut&lot=2")
            wait_js(page, "document.getElementById('trend-plot').naturalWidth > 500")
            assert page.locator("tr.outlier").count() > 0
            assert set(page.locator("tr.outlier td:nth-child(2)").all_inner_texts()) == {"cage-3"}
            screenshot(page, "lab-trend")
            page.click("text=Audit")
            body = page.inner_text("main")
            assert "runs with an expired instrument certificate (100)" in body
            assert (
                page.locator("table.lab").nth(2).locator("tbody tr td").first.inner_text()
                == "cage-3"
            )
            browser.close()
    finally:
        stop_child(server, first=signal.SIGTERM, wait_s=5.0)
    bare, bare_url = serve_process(rig_dirs[0])
    try:
        with owner_client(bare_url) as client:  # closed: its kept-alive socket too
            r = client.get("/lab")
        assert r.status_code == 404 and "rig serve --lab" in r.text
    finally:
        stop_child(bare, first=signal.SIGTERM, wait_s=5.0)
