"""A template typo fails loudly (issue 57): a name a template prints or loops over that the page
does not give is an error (500, one line naming it, ``rig.web.app.PageUndefined``) where it used
to render as an empty cell that every page test passed; testing a name the page gives only
sometimes (``{% if error %}``) stays false."""

from __future__ import annotations

import asyncio
import shutil
from pathlib import Path

import httpx
import pytest

import rig.web.app as web_app

pytestmark = pytest.mark.realtime


def runs_page(runs: Path) -> tuple[int, str]:
    """The runs page (the application in this process, over httpx's ASGI transport), from the
    templates where ``rig.web.app.HERE`` points."""
    app = web_app.create_app(runs, access_token="t")

    async def get() -> httpx.Response:
        transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1",
                                     headers={"authorization": "Bearer t"}) as client:  # fmt: skip
            return await client.get("/")

    reply = asyncio.run(get())
    return reply.status_code, reply.text


def test_a_name_the_page_does_not_give_is_an_error_not_an_empty_cell(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    site = tmp_path / "web"
    shutil.copytree(Path(web_app.__file__).parent, site)
    runs = tmp_path / "runs"
    runs.mkdir()
    monkeypatch.setattr(web_app, "HERE", site)
    status, body = runs_page(runs)
    assert status == 200 and str(runs) in body
    page = site / "templates" / "runs.html"
    page.write_text(page.read_text().replace("{{ runs_dir }}", "{{ run_dir }}", 1))
    status, body = runs_page(runs)
    assert status == 500 and "UndefinedError" in body and "'run_dir' is undefined" in body, body
