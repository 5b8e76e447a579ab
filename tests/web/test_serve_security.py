"""`rig serve` over real HTTP on loopback: what it serves, and what it refuses.

Loopback by default, a token for any other address, no cross-site writes, no file outside a run
folder's own downloads; exports of a finished run.
"""

from __future__ import annotations

import io
import signal
import subprocess
import sys
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from rig.child_process import stop_child
from rig.store import run_control
from tests.simrun import TINY_PROCEDURE, run_on_sim
from tests.web.conftest import owner_client, serve_process

pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("served")
    outcome = run_on_sim(folder, TINY_PROCEDURE)
    assert outcome.status == "complete", outcome.reason
    (folder / "secret.txt").write_text("not for the page")
    return folder / "runs"


@pytest.fixture(scope="module")
def served(runs: Path) -> Iterator[str]:
    """The address `rig serve` printed (with its access token)."""
    proc, url = serve_process(runs)
    try:
        yield url
    finally:
        stop_child(proc, first=signal.SIGTERM, wait_s=5.0)


@pytest.fixture(scope="module")
def client(served: str) -> Iterator[httpx.Client]:
    """The owner's client (it has the token)."""
    with owner_client(served) as c:
        yield c


@pytest.fixture(scope="module")
def server(client: httpx.Client) -> str:
    return str(client.base_url).rstrip("/")


def run_id(runs: Path) -> str:
    return next(runs.iterdir()).name


def csrf(client: httpx.Client, rid: str) -> str:
    html = client.get(f"/runs/{rid}").text
    return html.split('name="rig-csrf" content="')[1].split('"')[0]


def test_lists_and_exports_a_finished_run(client: httpx.Client, runs: Path) -> None:
    rid = run_id(runs)
    rows = client.get("/api/runs").json()
    assert [(r["run_id"], r["status"], r["verdict"]) for r in rows] == [(rid, "complete", "PASS")]
    assert client.get("/api/runs", params={"q": "sn-0042"}).json() == rows
    assert client.get("/api/runs", params={"q": "SN-9999"}).json() == []
    page = client.get(f"/runs/{rid}")
    assert page.status_code == 200 and "DUT noise at null field" in page.text
    result = client.get(f"/runs/{rid}/export/json").json()
    assert result["verdict"]["overall"] == "PASS" and "dut_noise_nt" in result["noise floor"]
    z = zipfile.ZipFile(io.BytesIO(client.get(f"/runs/{rid}/export/csv").content))
    assert "samples_aligned.csv" in z.namelist()
    h5 = client.get(f"/runs/{rid}/export/hdf5")
    assert h5.status_code == 200 and h5.content[:8] == b"\x89HDF\r\n\x1a\n"
    assert client.get(f"/runs/{rid}/files/run.sqlite").content[:15] == b"SQLite format 3"
    cage = client.get("/cage")
    assert cage.status_code == 200 and "rig serve --rig" in cage.text


@pytest.mark.parametrize("path", [
    "/runs/{rid}/files/..%2F..%2Fsecret.txt",
    "/runs/{rid}/files/../../secret.txt",
    "/runs/..%2Fsecret.txt/files/run.sqlite",
    "/runs/{rid}/files/%2Fetc%2Fpasswd",
    "/runs/{rid}/files/.run.sqlite.new",
    "/runs/{rid}/files/live.json",
    "/runs/{rid}/export/..%2Fsecret",
    "/static/..%2F..%2Fapp.py",
    "/static/../app.py",
    "/runs/..%2F..%2F..%2Fetc/files/passwd",
])  # fmt: skip
def test_nothing_outside_a_run_folders_downloads_is_served(
    client: httpx.Client, runs: Path, path: str
) -> None:
    r = client.get(path.format(rid=run_id(runs)))
    assert r.status_code == 404, (path, r.status_code, r.text[:100])
    assert "not for the page" not in r.text and "root:" not in r.text


def test_state_changes_need_the_pages_secret_and_origin(
    client: httpx.Client, server: str, runs: Path
) -> None:
    rid = run_id(runs)
    url = f"/runs/{rid}/control"
    body = {"action": "abort"}
    # a form or script on another site: no secret header, or a foreign Origin
    assert client.post(url, json=body).status_code == 403
    assert client.post(url, data={"action": "abort"}).status_code == 403
    secret = csrf(client, rid)
    r = client.post(url, json=body, headers={"x-rig-csrf": secret, "origin": "http://evil.example"})
    assert r.status_code == 403
    assert client.post(url, json=body, headers={"x-rig-csrf": "guess"}).status_code == 403
    # the page's own request is accepted, but this run has ended: nothing to operate
    r = client.post(url, json=body, headers={"x-rig-csrf": secret, "origin": server})
    assert r.status_code == 409 and "ended" in r.json()["error"]
    assert not (runs / rid / run_control.CONTROL_DIR).exists()


def test_loopback_server_refuses_other_host_names(client: httpx.Client) -> None:
    """A DNS name of an attacker's that points at 127.0.0.1 does not reach the page."""
    r = client.get("/", headers={"host": "attacker.example:80"})
    assert r.status_code == 421
    assert client.get("/", headers={"host": "localhost"}).status_code == 200


def test_other_addresses_need_a_flag_and_then_a_token(runs: Path) -> None:
    refused = subprocess.run([sys.executable, "-m", "rig.cli", "serve", "--runs-dir", str(runs),
                              "--host", "0.0.0.0", "--port", "0"],
                             capture_output=True, text=True, timeout=60)  # fmt: skip
    assert refused.returncode == 2
    assert refused.stderr.count("\n") == 1 and "--allow-remote" in refused.stderr
    proc, url = serve_process(runs, "--host", "0.0.0.0", "--allow-remote")
    try:
        assert "?token=" in url
        base, token = url.split("?token=")
        local = base.replace("0.0.0.0", "127.0.0.1")
        assert httpx.get(f"{local}api/runs").status_code == 401
        assert httpx.get(f"{local}api/runs", params={"token": "wrong"}).status_code == 401
        with httpx.Client(follow_redirects=True) as client:
            first = client.get(f"{local}?token={token}")  # follows the redirect, keeps the cookie
            assert first.status_code == 200 and token not in str(first.url)
            assert client.get(f"{local}api/runs").status_code == 200
    finally:
        stop_child(proc, first=signal.SIGTERM, wait_s=5.0)


def test_control_requests_reach_a_running_run_only_whole(tmp_path: Path) -> None:
    """The request box: written under a temporary name, taken oldest first, bad ones dropped."""
    run_control.request(tmp_path, "pause")
    run_control.request(tmp_path, "answer", prompt=3, yes=True)
    (tmp_path / run_control.CONTROL_DIR / "junk.json").write_text("{not json")
    (tmp_path / run_control.CONTROL_DIR / ".half.json.tmp").write_text('{"action": "abort"}')
    taken = run_control.take_requests(tmp_path)
    assert [(r["action"], r.get("prompt"), r.get("yes")) for r in taken] == [
        ("pause", None, None), ("answer", 3, True)]  # fmt: skip
    assert run_control.take_requests(tmp_path) == []
    with pytest.raises(Exception, match="unknown run request"):
        run_control.request(tmp_path, "explode")


def test_a_sigterm_the_moment_the_address_is_printed_leaves_no_access_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The address is printed before the page is built (imports, templates: about a second); a
    caller that stops the server at once must not find the token left behind (a clean-clone CI run
    did, while the SIGTERM handler was installed only after the page was built)."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    for _ in range(3):
        proc, url = serve_process(tmp_path)
        proc.send_signal(signal.SIGTERM)
        assert stop_child(proc, first=signal.SIGTERM, wait_s=60.0) == -signal.SIGTERM
        port = url.split("://", 1)[1].split("/", 1)[0].rsplit(":", 1)[1]
        assert not (tmp_path / "rig-serve" / f"{port}.url").exists()
        assert (tmp_path / "rig-serve").is_dir()  # it was written, then removed
