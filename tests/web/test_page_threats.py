"""The page against the attacks of issue 29, over real HTTP on loopback and in Debian's chromium.

Another local account (``setpriv`` to uid 65534) neither sees nor operates the page; no page of
another origin frames it; a 200 MB body is refused before it is read; bad numbers in an answer are
a 400; links planted in run folders are not followed; a damaged run.sqlite hides no other run; run
ids with ``?``, ``#`` and ``%`` link correctly.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import sqlite3
import stat
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from http.server import HTTPServer, SimpleHTTPRequestHandler
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlsplit

import httpx
import pytest

from rig.child_process import stop_child
from rig.store import run_control
from rig.web.app import segment
from rig.web.security import MAX_BODY
from tests.simrun import TINY_PROCEDURE, run_on_sim
from tests.web.conftest import owner_client, serve_process, split_token

pytestmark = pytest.mark.realtime

NOBODY = 65534
ODD_IDS = ["run?q=1", "run#frag", "run%41", "run with space"]
SECRET = "TOP SECRET, not for the page"


def as_nobody(*argv: str, **kwargs: Any) -> subprocess.CompletedProcess[str]:
    """``argv`` run as another local account (uid/gid 65534, no groups)."""
    cmd = ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", *argv]
    try:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=60, **kwargs)
    except FileNotFoundError:
        pytest.skip("setpriv (util-linux) is needed to act as another account")


def nobody_can_run() -> None:
    probe = as_nobody("true")
    if probe.returncode != 0:
        pytest.skip(f"cannot act as uid {NOBODY} here: {probe.stderr.strip()}")


def shared_folder(name: str) -> Path:
    """A folder every account can reach (pytest's own are 0700), removed by the caller."""
    folder = Path(tempfile.mkdtemp(prefix=f"rig-{name}-", dir="/tmp"))
    folder.chmod(0o755)
    return folder


def set_meta(folder: Path, **values: Any) -> None:
    con = sqlite3.connect(folder / "run.sqlite")
    with con:
        for k, v in values.items():
            con.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)", (k, json.dumps(v)))
    con.close()


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """A runs folder with a closed run, copies of it under odd ids, one that looks running (this
    process's pid), a damaged one, a linked one and planted links; `rig serve` on it."""
    base = tmp_path_factory.mktemp("threats")
    outcome = run_on_sim(base, TINY_PROCEDURE)
    assert outcome.status == "complete", outcome.reason
    runs = base / "runs"
    good = outcome.folder
    for rid in ODD_IDS:
        shutil.copytree(good, runs / rid)
    running = runs / "20990101-000000-RUNNING"
    shutil.copytree(good, running)
    set_meta(running, status="running", pid=os.getpid())
    damaged = runs / "20990101-000001-DAMAGED"
    shutil.copytree(good, damaged)
    with open(damaged / "run.sqlite", "r+b") as fh:
        fh.truncate(3000)  # the header survives, the tables do not
    secret = base / "secret.txt"
    secret.write_text(SECRET)
    (good / "x.png").symlink_to("/etc/shadow")
    (good / "y.png").symlink_to(secret)
    (good / "plot.json").symlink_to(secret)
    os.mkfifo(good / "z.csv")  # a reader that opened it would wait for a writer forever
    os.symlink(good, runs / "20990101-000002-LINKED")
    xdg = base / "xdg"
    xdg.mkdir(mode=0o700)
    old = os.environ.get("XDG_RUNTIME_DIR")
    os.environ["XDG_RUNTIME_DIR"] = str(xdg)
    try:
        proc, url = serve_process(runs)
    finally:
        if old is None:
            os.environ.pop("XDG_RUNTIME_DIR")
        else:
            os.environ["XDG_RUNTIME_DIR"] = old
    try:
        with owner_client(url) as client:
            yield {"url": url, "client": client, "runs": runs, "good": good, "xdg": xdg,
                   "running": running, "damaged": damaged, "proc": proc}  # fmt: skip
    finally:
        stop_child(proc, first=signal.SIGTERM, wait_s=5.0)


def csrf(client: httpx.Client, rid: str) -> str:
    html = client.get(f"/runs/{quote(rid, safe='')}").text
    return html.split('name="rig-csrf" content="')[1].split('"')[0]


def one_line(text: str) -> bool:
    return text.count("\n") <= 1 and "Traceback" not in text and text.strip() != ""


# --- only the owner --------------------------------------------------------------------------------


def test_the_page_needs_its_access_token(site: dict[str, Any]) -> None:
    base, token = split_token(site["url"])
    plain = httpx.get(f"{base}/")
    assert plain.status_code == 401 and one_line(plain.text)
    assert "token" in plain.text and "rig-csrf" not in plain.text
    assert httpx.get(f"{base}/?token=wrong").status_code == 401
    assert httpx.get(f"{base}/static/app.js").status_code == 401
    assert httpx.get(f"{base}/", headers={"authorization": "Bearer wrong"}).status_code == 401
    first = httpx.get(f"{base}/runs/{quote(ODD_IDS[0], safe='')}?token={token}&x=1")
    assert first.status_code == 303
    assert first.headers["location"] == f"/runs/{quote(ODD_IDS[0], safe='')}?x=1"
    cookie = first.headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and token in cookie
    port = urlsplit(base).port
    assert cookie.startswith(f"rig_token_{port}=")
    again = httpx.get(f"{base}/", cookies={f"rig_token_{port}": token})
    assert again.status_code == 200 and "rig-csrf" in again.text
    # the owner's other tools find the address in a file only the owner can read
    access = site["xdg"] / "rig-serve" / f"{port}.url"
    assert access.read_text().strip() == site["url"]
    assert stat.S_IMODE(access.stat().st_mode) == 0o600
    assert stat.S_IMODE(access.parent.stat().st_mode) == 0o700


def test_another_account_neither_sees_nor_operates_the_page(site: dict[str, Any]) -> None:
    nobody_can_run()
    base, _ = split_token(site["url"])
    rid = quote(site["running"].name, safe="")
    for method, path in [("GET", "/"), ("GET", f"/runs/{rid}"), ("GET", "/api/runs"),
                         ("POST", f"/runs/{rid}/control")]:  # fmt: skip
        r = as_nobody("curl", "-s", "-X", method, "-H", "x-rig-csrf: guess", "-H",
                      "content-type: application/json", "--data-binary", '{"action":"abort"}'
                      if method == "POST" else "", "-w", "\n%{http_code}", f"{base}{path}")  # fmt: skip
        body, code = r.stdout.rsplit("\n", 1)
        assert code == "401", (path, r.stdout, r.stderr)
        assert "rig-csrf" not in body
    # the access file, in a folder the other account can reach: not readable
    shared = shared_folder("xdg")
    try:
        env = {**os.environ, "XDG_RUNTIME_DIR": str(shared)}
        proc = subprocess.Popen([sys.executable, "-m", "rig.cli", "serve", "--runs-dir",
                                 str(site["runs"]), "--port", "0"], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, env=env)  # fmt: skip
        try:
            assert proc.stdout is not None
            line = proc.stdout.readline().decode()
            port = urlsplit(line.split()[-1]).port
            access = shared / "rig-serve" / f"{port}.url"
            assert access.read_text().strip() == line.split()[-1]
            r = as_nobody("cat", str(access))
            assert r.returncode != 0 and "token" not in r.stdout
            assert "Permission denied" in r.stderr
        finally:  # a clean end (beside two hogs and four workers once over 5 s: then killed)
            stop_child(proc, first=signal.SIGTERM, wait_s=60.0)
        assert not access.exists()  # removed when the server ends
    finally:
        shutil.rmtree(shared)


def test_the_control_box_takes_only_the_owners_requests(tmp_path: Path) -> None:
    """control/ is 0700; a request of another account, a link, or a box others can write or own
    is not taken, and each reason is reported (the run records it once)."""
    box = run_control.open_box(tmp_path)
    assert stat.S_IMODE(box.stat().st_mode) == 0o700
    run_control.request(tmp_path, "pause")
    (only,) = box.iterdir()
    assert stat.S_IMODE(only.stat().st_mode) == 0o600
    # a request file of another account (as root could leave there)
    foreign = box / "00000000000000000001-foreign.json"
    foreign.write_text('{"action": "abort"}')
    os.chown(foreign, NOBODY, NOBODY)
    # a link to a file that holds a request: not read through, its target left alone
    target = tmp_path / "elsewhere.json"
    target.write_text('{"action": "abort"}')
    (box / "00000000000000000002-link.json").symlink_to(target)
    refused: list[str] = []
    taken = run_control.take_requests(tmp_path, refused)
    assert [r["action"] for r in taken] == ["pause"]
    assert f"control requests from uid {NOBODY} ignored" in refused[0]
    assert "link" in refused[1] and len(refused) == 2
    assert target.read_text() == '{"action": "abort"}' and list(box.iterdir()) == []
    # a box others may write to, or that another account owns: nothing in it is taken
    run_control.request(tmp_path, "abort")
    box.chmod(0o777)
    refused = []
    assert run_control.take_requests(tmp_path, refused) == []
    assert "other accounts may write to it" in refused[0]
    with pytest.raises(Exception, match="not used"):
        run_control.request(tmp_path, "pause")
    box.chmod(0o700)
    os.chown(box, NOBODY, NOBODY)
    refused = []
    assert run_control.take_requests(tmp_path, refused) == []
    assert f"from uid {NOBODY} ignored" in refused[0]
    os.chown(box, 0, 0)
    assert [r["action"] for r in run_control.take_requests(tmp_path)] == ["abort"]


# --- framing, bodies, numbers ----------------------------------------------------------------------


def test_every_response_refuses_framing_and_sniffing(site: dict[str, Any]) -> None:
    client: httpx.Client = site["client"]
    base, _ = split_token(site["url"])
    good = quote(site["good"].name, safe="")
    answers = [client.get("/"), client.get("/static/app.js"), client.get(f"/runs/{good}"),
               client.get("/runs/nothing-here"), httpx.get(f"{base}/"),
               client.get("/", headers={"host": "evil.example"}),
               client.post(f"/runs/{good}/control", content=b"x" * (MAX_BODY + 1),
                           headers={"x-rig-csrf": csrf(client, site["good"].name)})]  # fmt: skip
    assert [r.status_code for r in answers] == [200, 200, 200, 404, 401, 421, 413]
    for r in answers:
        csp = r.headers["content-security-policy"]
        assert "frame-ancestors 'none'" in csp, (r.url, csp)
        assert r.headers["x-frame-options"] == "DENY"
        assert r.headers["x-content-type-options"] == "nosniff"
    assert "script-src 'self'" in answers[0].headers["content-security-policy"]
    # the one file the run page frames itself: its own origin only, and no script runs in it
    if (site["good"] / "report.html").exists():
        report = client.get(f"/runs/{good}/files/report.html")
        assert report.headers["x-frame-options"] == "SAMEORIGIN"
        policy = report.headers["content-security-policy"]
        assert "frame-ancestors 'self'" in policy and policy.startswith("default-src 'none'")


def _raw_post(port: int, head: bytes, chunks: Iterator[bytes]) -> tuple[bytes, int, float]:
    """Send ``head`` then ``chunks`` until the server answers; returns its answer, the bytes of
    body sent and the seconds from the first byte to the answer."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    sent = 0
    t0 = time.monotonic()
    answer = b""
    try:
        sock.sendall(head)
        sock.setblocking(False)
        for chunk in chunks:
            try:
                answer += sock.recv(65536)
                break  # the server has answered
            except BlockingIOError:
                pass
            except ConnectionError:
                break
            view = memoryview(chunk)
            while view:
                try:
                    view = view[sock.send(view) :]
                except BlockingIOError:
                    time.sleep(0.001)
                    try:
                        answer += sock.recv(65536)
                    except BlockingIOError:
                        continue
                    except ConnectionError:
                        pass
                    view = view[:0]
                except ConnectionError:
                    view = view[:0]
            sent += len(chunk)
            if answer:
                break
        sock.setblocking(True)
        sock.settimeout(30)
        while b"\r\n\r\n" not in answer:
            try:
                more = sock.recv(65536)
            except ConnectionError:
                break
            if not more:
                break
            answer += more
    finally:
        sock.close()
    return answer, sent, time.monotonic() - t0


def peak_rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    raise AssertionError("no VmHWM")


@pytest.mark.parametrize("framing", ["content-length", "chunked"])
def test_a_200_mb_post_is_refused_before_it_is_read(site: dict[str, Any], framing: str) -> None:
    client: httpx.Client = site["client"]
    base, token = split_token(site["url"])
    port = urlsplit(base).port
    assert port is not None
    rid = quote(site["running"].name, safe="")
    secret = csrf(client, site["running"].name)
    size = 200 * 1024 * 1024
    length = (f"content-length: {size}" if framing == "content-length"
              else "transfer-encoding: chunked")  # fmt: skip
    head = (f"POST /runs/{rid}/control HTTP/1.1\r\nhost: 127.0.0.1:{port}\r\n"
            f"authorization: Bearer {token}\r\nx-rig-csrf: {secret}\r\n"
            f"content-type: application/json\r\n{length}\r\n\r\n").encode()  # fmt: skip
    block = b"[" * 65536
    chunk = block if framing == "content-length" else b"10000\r\n" + block + b"\r\n"
    before = peak_rss_kib(site["proc"].pid)
    answer, sent, seconds = _raw_post(port, head, iter([chunk] * (size // 65536)))
    after = peak_rss_kib(site["proc"].pid)
    print(f"{framing}: 413 after {sent / 1e6:.1f} MB sent, {seconds * 1000:.0f} ms;"
          f" server peak RSS {before / 1024:.0f} -> {after / 1024:.0f} MiB")  # fmt: skip
    assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
    assert sent < 32 * 1024 * 1024  # refused long before 200 MB were sent
    assert after - before < 32 * 1024  # KiB: the body was never held
    assert not (site["running"] / run_control.CONTROL_DIR).exists() or not list(
        (site["running"] / run_control.CONTROL_DIR).iterdir()
    )


@pytest.mark.parametrize("body", [
    b'{"action": "answer", "prompt": Infinity, "yes": true}',
    b'{"action": "answer", "prompt": NaN, "yes": true}',
    b'{"action": "answer", "prompt": -Infinity, "yes": true}',
    b'{"action": "answer", "prompt": 1e400, "yes": true}',
    b'{"action": "answer", "prompt": 123456789012345678901234567890, "yes": true}',
    b'{"action": "answer", "prompt": -1, "yes": true}',
    b'{"action": "answer", "prompt": "1", "yes": true}',
    b'{"action": "answer", "prompt": true, "yes": true}',
    b'{"action": "answer", "prompt": 1, "yes": "no"}',
    b'{"action": "explode"}',
    b'["abort"]',
    b"[" * 20000 + b"]" * 20000,
    b"\xff\xfe",
    b"",
])  # fmt: skip
def test_bad_numbers_in_an_answer_are_a_400_of_one_line(site: dict[str, Any], body: bytes) -> None:
    client: httpx.Client = site["client"]
    rid = site["running"].name
    r = client.post(f"/runs/{quote(rid, safe='')}/control", content=body,
                    headers={"x-rig-csrf": csrf(client, rid), "content-type": "application/json"})  # fmt: skip
    assert r.status_code == 400, r.text
    assert one_line(r.json()["error"]) and r.json()["error"].startswith("bad control request")
    assert not list((site["running"] / run_control.CONTROL_DIR).glob("*.json"))


def test_a_good_answer_is_queued_in_a_private_box(site: dict[str, Any]) -> None:
    client: httpx.Client = site["client"]
    rid = site["running"].name
    r = client.post(f"/runs/{quote(rid, safe='')}/control", headers={"x-rig-csrf": csrf(client, rid)},
                    json={"action": "answer", "prompt": 2, "yes": True})  # fmt: skip
    assert r.status_code == 200 and r.json() == {"queued": "answer"}
    box = site["running"] / run_control.CONTROL_DIR
    assert stat.S_IMODE(box.stat().st_mode) == 0o700
    (req,) = run_control.take_requests(site["running"])
    assert (req["action"], req["prompt"], req["yes"]) == ("answer", 2, True)


# --- links, damage, odd ids ------------------------------------------------------------------------


def test_links_in_run_folders_are_not_followed(site: dict[str, Any]) -> None:
    client: httpx.Client = site["client"]
    good = quote(site["good"].name, safe="")
    page = client.get(f"/runs/{good}").text
    for name in ("x.png", "y.png", "plot.json", "z.csv"):
        r = client.get(f"/runs/{good}/files/{name}")
        assert r.status_code == 404 and one_line(r.text), name
        assert "root:" not in r.text and SECRET not in r.text
        assert f"/files/{name}" not in page  # not offered either
    assert client.get(f"/runs/{good}/files/run.sqlite").content[:15] == b"SQLite format 3"
    listed = [r["run_id"] for r in client.get("/api/runs").json()]
    assert "20990101-000002-LINKED" not in listed and site["good"].name in listed
    assert client.get("/runs/20990101-000002-LINKED").status_code == 404
    assert client.get("/runs/20990101-000002-LINKED/files/run.sqlite").status_code == 404


def test_a_damaged_run_is_shown_as_damaged_and_hides_no_other(site: dict[str, Any]) -> None:
    client: httpx.Client = site["client"]
    rows = {r["run_id"]: r for r in client.get("/api/runs").json()}
    assert site["good"].name in rows and all(rid in rows for rid in ODD_IDS)
    bad = rows[site["damaged"].name]
    assert bad["status"] == "damaged" and "rig verify" in bad["reason"] and one_line(bad["reason"])
    listing = client.get("/").text
    assert 'class="status-damaged" title="cannot read run.sqlite' in listing
    damaged = quote(site["damaged"].name, safe="")
    page = client.get(f"/runs/{damaged}")
    assert page.status_code == 500 and "is damaged" in page.text
    assert "Traceback" not in page.text and 'id="message"' in page.text
    api = client.get(f"/api/runs/{damaged}")
    assert api.status_code == 500 and one_line(api.json()["error"])
    export = client.get(f"/runs/{damaged}/export/json")
    assert export.status_code == 500 and one_line(export.text)
    r = client.post(f"/runs/{damaged}/control", json={"action": "abort"},
                    headers={"x-rig-csrf": csrf(client, site["good"].name)})  # fmt: skip
    assert r.status_code == 500 and one_line(r.json()["error"])


def test_path_segments_are_quoted() -> None:
    assert segment("run?q=1") == "run%3Fq%3D1" and segment("SN/01") == "SN%2F01"
    assert segment("a#b%c d") == "a%23b%25c%20d"


def test_odd_run_ids_link_correctly_in_the_browser(site: dict[str, Any], browser: Any) -> None:
    base, _ = split_token(site["url"])
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    page.goto(site["url"])
    assert "token=" not in page.url
    for rid in ODD_IDS:
        page.goto(f"{base}/")
        row = page.locator("#runs tbody tr[data-run]").filter(
            has=page.get_by_role("link", name=rid, exact=True)
        )
        row.get_by_role("link", name=rid, exact=True).click()
        page.wait_for_selector("h1 small")
        assert page.inner_text("h1 small") == rid, page.url
        hrefs = page.eval_on_selector_all("#files a, #export-json", "els => els.map(e => e.href)")
        assert len(hrefs) >= 3
        for href in hrefs:
            assert page.request.get(href).status == 200, href
    # the list the script rebuilds every 2 s links the same way
    page.goto(f"{base}/")
    page.evaluate("document.querySelector('#runs tbody').replaceChildren()")
    page.wait_for_selector(f"#runs tbody tr[data-run='{ODD_IDS[1]}'] a", timeout=10_000)
    page.click(f"#runs tbody tr[data-run='{ODD_IDS[1]}'] a")
    page.wait_for_selector("h1 small")
    assert page.inner_text("h1 small") == ODD_IDS[1]
    page.close()


def test_a_page_of_another_origin_cannot_frame_the_run_page(
    site: dict[str, Any], browser: Any, tmp_path: Path
) -> None:
    """The owner has the cookie (same site: another port of 127.0.0.1 gets it sent along); a page
    served from that other port frames the run page and one of its own: only its own loads."""
    base, _ = split_token(site["url"])
    target = f"{base}/runs/{quote(site['running'].name, safe='')}"
    (tmp_path / "own.html").write_text("<p id=own>own frame</p>")
    (tmp_path / "attack.html").write_text(
        f'<iframe id="victim" src="{target}"></iframe><iframe id="own" src="/own.html"></iframe>'
    )

    class Quiet(SimpleHTTPRequestHandler):
        def __init__(self, *a: Any, **k: Any) -> None:
            super().__init__(*a, directory=str(tmp_path), **k)

        def log_message(self, *a: Any) -> None:
            pass

    attacker = HTTPServer(("127.0.0.1", 0), Quiet)
    threading.Thread(target=attacker.serve_forever, daemon=True).start()
    try:
        page = browser.new_page()
        page.goto(site["url"])  # the owner's browser holds the access cookie
        assert page.locator("#runs").count() == 1
        answers: list[Any] = []
        page.on("response", lambda r: answers.append(r) if r.url == target else None)
        page.goto(f"http://127.0.0.1:{attacker.server_address[1]}/attack.html")
        page.wait_for_load_state("load")
        own = page.frame_locator("#own").locator("#own")
        assert own.inner_text() == "own frame"  # frames work on that page
        # the cookie went along and the server answered with the page, but the browser did not
        # show it in the frame: the headers refused it
        deadline = time.monotonic() + 10
        while not answers:
            assert time.monotonic() < deadline, "the framed request never went out"
            page.wait_for_timeout(100)
        assert answers[0].status == 200
        assert "frame-ancestors 'none'" in answers[0].headers["content-security-policy"]
        assert page.frame_locator("#victim").locator("#abort").count() == 0
        assert all(f.locator("#abort").count() == 0 for f in page.frames)
        page.close()
    finally:
        attacker.shutdown()
        attacker.server_close()


# --- a live run on the simulated cage --------------------------------------------------------------

NOBODY_TRIES = r"""
import json, os, sys
box = sys.argv[1]
try:
    open(os.path.join(box, "00000000000000000000-in.json"), "w").write('{"action": "abort"}')
    print("wrote into the run's control folder")
except PermissionError:
    print("denied")
os.rename(box, box + ".moved")  # the run folder is writable by all: its entries can be moved
os.mkdir(box, 0o777)
for i, body in enumerate([{"action": "answer", "prompt": 1, "yes": True}, {"action": "abort"}]):
    with open(os.path.join(box, f"{i:020d}-nobody.json"), "w") as fh:
        json.dump(body, fh)
print("planted")
"""


def test_another_account_cannot_answer_or_abort_a_live_run(tmp_path: Path) -> None:
    """A run in a runs folder every account may write to, waiting at its first prompt: another
    account gets 401 from the page and cannot write into control/; the control folder it puts in
    place of the run's is ignored (recorded once); the owner then aborts from the page."""
    from tests.simproc import sim_process

    nobody_can_run()
    shared = shared_folder("runs")
    runs = shared / "runs"
    runs.mkdir(mode=0o777)
    runs.chmod(0o777)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)}
    try:
        (tmp_path / "sim").mkdir()
        with sim_process(tmp_path / "sim") as (rig_toml, _):
            proc = subprocess.Popen([sys.executable, "-m", "rig.cli", "run", "smoke", "--rig",
                                     str(rig_toml), "--runs-dir", str(runs), "--serve", "--port",
                                     "0"], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE, env=env)  # fmt: skip
            try:
                _another_account_at_the_prompt(proc, runs)
            finally:
                stop_child(
                    proc, first=signal.SIGTERM, wait_s=10.0
                )  # ended or not: its pipes closed
    finally:
        shutil.rmtree(shared)


def _another_account_at_the_prompt(proc: subprocess.Popen[bytes], runs: Path) -> None:
    from tests.web.conftest import read_url

    url = read_url(proc, "watch and operate this run at")
    run_page = read_url(proc, "this run's page:")
    folder = runs / urlsplit(run_page).path.rsplit("/", 1)[1]
    folder.chmod(0o777)  # as a group-writable umask or a shared folder would leave it
    deadline = time.monotonic() + 60
    while "prompt" not in (run_control.read_live(folder) or {}):
        assert proc.poll() is None and time.monotonic() < deadline, "no prompt on the page"
        time.sleep(0.1)
    box = folder / run_control.CONTROL_DIR
    assert stat.S_IMODE(box.stat().st_mode) == 0o700
    # through the page: no token, no page, no answer
    base, token = split_token(url)
    path = urlsplit(run_page).path
    for argv in (["curl", "-s", "-w", "\n%{http_code}", f"{base}{path}"],
                 ["curl", "-s", "-w", "\n%{http_code}", "-H", "x-rig-csrf: guess", "-H",
                  "content-type: application/json", "--data-binary",
                  '{"action": "answer", "prompt": 1, "yes": true}', f"{base}{path}/control"]):  # fmt: skip
        r = as_nobody(*argv)
        assert r.stdout.rsplit("\n", 1)[-1] == "401", r.stdout
    # through control/: the folder is the owner's 0700; a folder put in its place is ignored
    python = "/usr/bin/python3"  # the system's: a pyenv shim under /root is not theirs to run
    if not Path(python).exists():
        pytest.skip("another account needs /usr/bin/python3 to write into the run folder")
    tried = as_nobody(python, "-c", NOBODY_TRIES, str(box))
    assert tried.stdout.split() == ["denied", "planted"], tried.stderr
    ignored = f"control requests from uid {NOBODY} ignored"
    deadline = time.monotonic() + 30
    while not any(ignored in e["message"] for e in run_control.read_live(folder)["events"]):
        assert time.monotonic() < deadline, "the ignored requests were not recorded"
        time.sleep(0.1)
    time.sleep(1.0)  # ten more polls of the box
    state = run_control.read_live(folder)
    assert state["status"] == "running" and state["prompt"]["id"] == 1 and proc.poll() is None
    # the owner's page cannot use a box another account owns: it says so in one line
    with httpx.Client(base_url=base, headers={"authorization": f"Bearer {token}"}) as owner:
        html = owner.get(path).text
        secret = html.split('name="rig-csrf" content="')[1].split('"')[0]
        r = owner.post(f"{path}/control", json={"action": "abort"}, headers={"x-rig-csrf": secret})
        assert r.status_code == 409 and "not used" in r.json()["error"]
        shutil.rmtree(box)
        r = owner.post(f"{path}/control", json={"action": "abort"}, headers={"x-rig-csrf": secret})
        assert r.status_code == 200
    assert proc.wait(timeout=60) == 130
    con = sqlite3.connect(folder / "run.sqlite")
    meta = {k: json.loads(v) for k, v in con.execute("SELECT key, value FROM meta")}
    events = [m for (m,) in con.execute("SELECT message FROM events")]
    con.close()
    assert meta["status"] == "aborted" and meta["reason"] == "aborted from the web page"
    assert sum(ignored in m for m in events) == 1, events
    assert not any("confirmed" in m for m in events)


def test_a_lab_serial_with_a_slash_reaches_its_page(tmp_path: Path) -> None:
    """``/lab/dut/SN%2F01`` is the DUT page of ``SN/01`` (here the index is down: 503, one line
    naming it), not a 404 of a path that does not exist."""
    proc, url = serve_process(tmp_path, "--lab", "postgresql://rig@127.0.0.1:1/nothing")
    try:
        with owner_client(url) as client:
            for serial in ("SN/01", "SN?1#2%3"):
                r = client.get(f"/lab/dut/{segment(serial)}")
                assert r.status_code == 503, (serial, r.status_code)
                assert 'id="lab-error"' in r.text
            assert client.get("/lab/nothing/here").status_code == 404
    finally:
        stop_child(proc, first=signal.SIGTERM, wait_s=5.0)
