"""The lab index's refusals on the page (``/lab/refusals``, rig/web/lab_views/refusals.py: one
module and one line in the view registry), in Debian's chromium against a real PostgreSQL."""

from __future__ import annotations

import json
import signal
import sqlite3
from pathlib import Path

import pytest

from bench.labfixture import generate_runs
from rig.lab.sync import run_folders, sync_runs

pytestmark = pytest.mark.services


def test_the_refusals_page_lists_every_refused_run(lab_url: str, tmp_path: Path) -> None:
    from playwright.sync_api import sync_playwright

    from rig.child_process import stop_child
    from tests.web.conftest import CHROMIUM_ARGS, chromium_path, screenshot, serve_process

    runs = tmp_path / "runs"
    folders = generate_runs(runs, 3, rig="cage-1", seed=11)
    forged = folders[1]
    con = sqlite3.connect(forged / "run.sqlite")  # its verdict changed after the seal
    con.execute("UPDATE results SET value = ? WHERE name = 'verdict'",
                (json.dumps({"overall": "PASS", "criteria": []}),))  # fmt: skip
    con.commit()
    con.close()
    for _ in range(2):  # two syncs refuse it: two attempts
        assert len(sync_runs(lab_url, run_folders(runs)).refused) == 1
    server, url = serve_process(runs, "--lab", lab_url)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.goto(url)
            page.click("nav >> text=Lab")
            page.click("p.tabs >> text=Refusals")
            assert page.inner_text("#lab-title") == "Runs the lab index refused"
            assert page.url.split("?")[0].endswith("/lab/refusals")
            rows = page.locator("table.lab tbody tr")
            assert rows.count() == 1
            cells = dict(zip(page.locator("table.lab thead th").all_inner_texts(),
                             rows.first.locator("td").all_inner_texts(), strict=True))  # fmt: skip
            assert cells["run_id"] == forged.name and cells["rig"] == "cage-1"
            assert cells["kind"] == "changed since sealed" and cells["attempts"] == "2"
            assert "data changed since the run was sealed" in cells["reason"]
            screenshot(page, "lab-refusals")
            page.click("p.tabs >> text=Audit")  # the other views keep their tabs
            assert page.inner_text("#lab-title") == "Lab audit"
            browser.close()
    finally:
        stop_child(server, first=signal.SIGTERM, wait_s=5.0)
