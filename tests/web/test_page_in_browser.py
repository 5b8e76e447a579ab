"""The web page in a real browser (Debian's chromium) against real runs on the simulated cage.

A run started with ``rig run --serve`` is watched and operated from the page: the live plot gains
points, an operator prompt answered on the page lets the run go on, abort from the page leaves
every output off; ``rig serve`` then lists the finished run with its verdict and opens its report.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers.transport.tty_watch import tty_stall_s, tty_watch
from rig.child_process import start_child, stop_child
from rig.store import RunReader
from tests.computer_delay import ComputerDelay
from tests.simproc import children, outputs
from tests.simproc import sim_process as start_sim
from tests.web.conftest import read_url, screenshot, serve_process, split_token, wait_js

pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, dict[str, Any]]]:
    with start_sim(tmp_path_factory.mktemp("sim")) as s:
        yield s


def start_run(rig_toml: Path, runs: Path, *args: str) -> tuple[subprocess.Popen[bytes], str]:
    """``rig run ... --serve --port 0`` without a terminal; returns it and the page address."""
    proc = start_child([sys.executable, "-m", "rig.cli", "run", *args, "--rig", str(rig_toml),
                        "--runs-dir", str(runs), "--serve", "--port", "0"],
                       stdin=subprocess.DEVNULL, stderr=subprocess.PIPE)  # fmt: skip
    return proc, read_url(proc, "watch and operate this run at")


def open_running_run(page: Any, url: str) -> None:
    """From the run browser, open the run in progress."""
    page.goto(url)
    page.wait_for_selector("td.status-running", timeout=30_000)
    page.click("#runs tbody tr[data-run] a")
    page.wait_for_selector("#live:not([hidden])")


def test_run_watched_and_prompt_answered_on_the_page_then_browsed(
    sim: tuple[Path, dict[str, Any]], browser: Any, tmp_path: Path
) -> None:
    rig_toml, _ = sim
    runs = tmp_path / "runs"
    proc, url = start_run(rig_toml, runs, "smoke")
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        open_running_run(page, url)
        # the shipped smoke procedure starts with a prompt: nobody at a terminal answers it
        page.wait_for_selector("#prompt:not([hidden])", timeout=30_000)
        assert "Mount DUT SN-0001" in page.inner_text("#prompt-text")
        screenshot(page, "prompt")
        page.click("#prompt-yes")
        page.wait_for_selector("#prompt", state="hidden", timeout=10_000)
        # the live plot gains points while the field steps run
        wait_js(page, "Number(document.getElementById('live').dataset.points || 0) >= 3", 30)
        first = int(page.get_attribute("#live", "data-points"))
        wait_js(page, f"Number(document.getElementById('live').dataset.points || 0) >= {first + 4}")
        assert page.inner_text("#step-line").startswith("step ")
        screenshot(page, "live-run")
        wait_js(page, "document.getElementById('live').dataset.finished === 'complete'", 120)
        assert proc.wait(timeout=60) == 0
    finally:
        stop_child(proc, first=signal.SIGTERM)  # ended or not: its pipes closed
    folder = next(runs.iterdir())
    reader = RunReader(folder)
    events = [m for _, _, m in reader.events()]
    reader.close()
    assert any("confirmed" in m and "Mount DUT" in m for m in events), events

    # later: the run browser lists it with its verdict and opens its report
    server, url = serve_process(runs)
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto(url)  # the address with its token: the page keeps it as a cookie
        assert "token=" not in page.url
        base, _ = split_token(url)
        row = page.locator(f"tr[data-run='{folder.name}']")
        assert row.locator("td.status-complete").inner_text() == "complete"
        assert row.locator("td.verdict-PASS").inner_text() == "PASS"
        page.fill("#filter", "no such serial")
        assert not row.is_visible()
        page.fill("#filter", "SN-0001")
        assert row.is_visible()
        screenshot(page, "run-browser")
        row.locator("a").click()
        assert page.inner_text("#verdict") == "PASS"
        assert "DUT noise at null field" in page.inner_text("#criteria")
        result = page.request.get(f"{base}/runs/{folder.name}/export/json").json()
        assert result["verdict"]["overall"] == "PASS"
        zipped = page.request.get(f"{base}/runs/{folder.name}/export/csv")
        assert zipped.ok and zipped.body()[:2] == b"PK"
        page.click("#open-report")
        page.wait_for_load_state()
        assert folder.name in page.content() or "SN-0001" in page.content()
        assert "PASS" in page.inner_text("body")
        screenshot(page, "report")
    finally:
        stop_child(server, first=signal.SIGTERM, wait_s=5.0)


def test_live_calibration_shows_the_forecast_beside_its_sigmas(
    sim: tuple[Path, dict[str, Any]], browser: Any, tmp_path: Path
) -> None:
    """The live calibration's panel: each 1-sigma, the plan's forecast at this many samples
    (rig check --predict's, at this run's noise) and the target, and when they will be met."""
    rig_toml, _ = sim
    runs = tmp_path / "runs"
    proc, url = start_run(rig_toml, runs, "live-calibration")
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        open_running_run(page, url)
        page.wait_for_selector("#prompt:not([hidden])", timeout=30_000)
        page.click("#prompt-yes")
        page.wait_for_selector("#cal-forecast:not([hidden])", timeout=90_000)
        wait_js(page, "document.getElementById('cal-forecast').textContent"
                      ".startsWith('forecast: targets met in about')", 60)  # fmt: skip
        assert page.inner_text("#cal thead").split()[:3] == ["value", "1", "sigma"]
        rows = page.locator("#cal tbody tr")
        assert rows.count() == 4  # bias, scale, non-orthogonality, current-to-bias
        forecast = [rows.nth(i).locator("td").nth(2).inner_text() for i in range(rows.count())]
        assert all(float(v) > 0 for v in forecast), forecast
        # the run's progress counts the step to its forecast stop, not its 60 s max_s
        wait_js(page, "Number((document.getElementById('step-line').textContent"
                      ".match(/of (\\d+) s/) || [0, 60])[1]) < 60", 30)  # fmt: skip
        screenshot(page, "live-forecast")
        # what the panel shows is seen: the run is stopped (a run followed to its end on the page
        # is the smoke test's), and the page follows it to that end
        proc.send_signal(signal.SIGTERM)
        wait_js(page, "document.getElementById('live').dataset.finished === 'aborted'", 60)
        assert proc.wait(timeout=60) == 130
    finally:
        stop_child(proc, first=signal.SIGTERM)  # ended or not: its pipes closed


def test_abort_from_the_page_leaves_every_output_off(
    sim: tuple[Path, dict[str, Any]], browser: Any, tmp_path: Path
) -> None:
    rig_toml, devices = sim
    tty_watch()  # the kernel's serial stalls are the computer's, not the page's time to safe
    runs = tmp_path / "runs"
    proc, url = start_run(rig_toml, runs, "dut-acceptance", "--yes")
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        confirmed: list[float] = []  # when the test, as the operator, said yes to "Abort the run?"
        page.on("dialog", lambda d: (d.accept(), confirmed.append(time.monotonic())))
        run_page = read_url(proc, "this run's page:", stream=proc.stderr)
        base, token = split_token(url)
        assert run_page.startswith(base) and "/runs/" in run_page and run_page.endswith(token)
        page.goto(run_page)  # the address the terminal printed for this run
        page.wait_for_selector("#live:not([hidden])")
        deadline = time.monotonic() + 120
        while not any(v == 1 for v in outputs(devices, tcp_only=True).values()):
            assert proc.poll() is None, "the run ended before its outputs were on"
            assert time.monotonic() < deadline, "no output came on"
            time.sleep(0.2)
        wait_js(page, "Number(document.getElementById('live').dataset.points || 0) >= 2", 30)
        # pause holds the schedule at the next command of a step with scheduled commands (the
        # cage characterization runs its own sequence to its end first); resume goes on
        wait_js(page, "/noise floor|noise spectrum|linearity|sweep/.test("
                      "document.getElementById('step-line').textContent)", 60)  # fmt: skip
        page.click("#pause")
        # held at the step's next scheduled command: up to a whole action away (a noise record,
        # a sweep point), longer on a busy computer (5 s was once too short beside CPU hogs)
        page.wait_for_selector("#paused-flag:not([hidden])", timeout=60_000)
        time.sleep(1.0)
        page.click("#resume")
        page.wait_for_selector("#paused-flag", state="hidden", timeout=30_000)
        # the run and its page server (a child) hand the abort on in turn, and this test looks:
        # time any of them waited, runnable, for a CPU was the computer's (a busy 2-core machine)
        t_click, computer = time.monotonic(), ComputerDelay(proc.pid, *children(proc.pid))
        page.click("#abort")
        while any(v == 1 for v in outputs(devices, tcp_only=True).values()):
            assert time.monotonic() - t_click < 10.0, "outputs still on 10 s after the abort"
        t_off = time.monotonic()
        waited = computer.cpu_s()
        # from the operator's yes to the confirmation: the browser's dialog and the round trip to
        # its driver before it are the test's tools, not the rig (seen: 1354 ms from the click)
        assert confirmed and confirmed[-1] >= t_click, "the abort was not confirmed"
        t_safe = t_off - confirmed[-1]
        held = tty_stall_s(confirmed[-1], t_off)
        print(f"time to safe after the page's abort: {t_safe * 1000:.0f} ms from the operator's"
              f" yes, {(t_off - t_click) * 1000:.0f} ms from the click ({held * 1000:.0f} ms of it"
              f" the kernel held serial data back; the run, its page server and this test waited"
              f" {waited * 1000:.0f} ms for a CPU)")  # fmt: skip
        wait_js(page, "document.getElementById('live').dataset.finished === 'aborted'", 30)
        screenshot(page, "aborted")
        assert proc.wait(timeout=60) == 130
    finally:
        stop_child(proc, first=signal.SIGTERM)  # ended or not: its pipes closed
    assert all(v == 0 for v in outputs(devices).values()), outputs(devices)
    reader = RunReader(next(runs.iterdir()))
    meta = reader.meta()
    events = [(lv, m) for _, lv, m in reader.events()]
    reader.close()
    assert meta["status"] == "aborted" and meta["reason"] == "aborted from the web page"
    assert ("operator", "paused") in events and ("operator", "resumed") in events
    # judged once the run has said when it took the abort (monotonic s, this computer's clock):
    # a slow time to safe then says whether the request or the safe path was slow
    noticed_ms = 1000.0 * (float(meta["t_end_detected"]) - confirmed[-1])
    assert t_safe - held - waited < 1.0, f"the run took the abort {noticed_ms:.0f} ms after the yes"


def test_prompt_answered_at_the_terminal_first(
    sim: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    """With a terminal the question is asked there too; the first answer (here the terminal's)
    counts and the page's question goes away."""
    import os
    import pty

    from rig.store.run_control import read_live

    rig_toml, _ = sim
    runs = tmp_path / "runs"
    master, slave = pty.openpty()
    proc = start_child([sys.executable, "-m", "rig.cli", "run", "smoke", "--rig", str(rig_toml),
                        "--runs-dir", str(runs), "--serve", "--port", "0"],
                       stdin=slave, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)  # fmt: skip
    os.close(slave)
    try:
        read_url(proc, "watch and operate this run at", stream=proc.stderr)
        deadline = time.monotonic() + 60
        while True:
            folders = list(runs.iterdir()) if runs.exists() else []
            state = read_live(folders[0]) if folders else None
            if state is not None and "prompt" in state:
                break
            assert time.monotonic() < deadline, "the page never showed the prompt"
            time.sleep(0.1)
        assert "Mount DUT SN-0001" in state["prompt"]["text"]
        os.write(master, b"y\n")
        code = proc.wait(timeout=90)
        assert proc.stderr is not None
        assert code == 0, proc.stderr.read().decode(errors="replace")[-2000:]  # why, if not
    finally:
        os.close(master)
        stop_child(proc, first=signal.SIGTERM)  # ended or not: its pipes closed
    final = read_live(folders[0])
    assert final is not None and final["status"] == "complete" and "prompt" not in final
