"""``rig serve``'s web application (Starlette): run browser, run pages, live view, cage status.

The server is a process of its own. It reads run folders (SQLite, ``live.json``) and writes
requests into a running run's ``control/`` folder (:mod:`rig.store.run_control`): a slow, stuck
or vanished browser can neither delay a command nor lose a sample (ADR 0016). Who may use it:
:mod:`rig.web.security` and the threat model in docs/web.md.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import math
import os
import shutil
import tempfile
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any, BinaryIO
from urllib.parse import quote

import jinja2
from starlette.applications import Starlette
from starlette.background import BackgroundTask
from starlette.requests import Request
from starlette.responses import (
    FileResponse,
    JSONResponse,
    Response,
    StreamingResponse,
)
from starlette.routing import BaseRoute, Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.templating import Jinja2Templates

from rig.errors import RigError
from rig.store import run_control, safe_files
from rig.store.run_control import read_live
from rig.web.runs_view import (
    DAMAGED,
    EXPORTS,
    damage,
    downloads,
    export_file,
    list_summaries,
    media_type,
    run_details,
    run_folder,
    summary_or_damaged,
)
from rig.web.security import FRAMED_FILE_CSP, Guard, new_secret

HERE = Path(__file__).parent
LIVE_POLL_S = 0.25
"""How often an open live stream looks at ``live.json`` (s)."""
FRAMED_FILES = ("report.html",)
"""Run files the run page shows in a frame of its own (allowed to be framed by the page only)."""
CHUNK = 256 * 1024


def segment(value: object) -> str:
    """``value`` quoted as one URL path segment (``/``, ``?``, ``#`` and ``%`` included)."""
    return quote(str(value), safe="")


def text(status: int, line: str) -> Response:
    """A plain-text answer of one line."""
    return Response(line.rstrip("\n") + "\n", status_code=status, media_type="text/plain")


def bad_request(line: str) -> JSONResponse:
    """A refused control request: 400 with one line."""
    return JSONResponse({"error": line}, status_code=400)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number the rig takes")


def parse_control(body: bytes) -> dict[str, Any]:
    """A control request's JSON, checked: ``action`` one of the known ones, ``prompt`` a whole
    number, ``yes`` true or false (ValueError naming the problem)."""
    try:
        value = json.loads(body, parse_constant=_no_constant)
    except RecursionError:
        raise ValueError("request nested too deep") from None
    except UnicodeDecodeError:
        raise ValueError("request is not UTF-8 JSON") from None
    if not isinstance(value, dict):
        raise ValueError('a control request is a JSON object: {"action": ...}')
    action = value.get("action")
    if action not in run_control.ACTIONS:
        raise ValueError(f"unknown action; use one of {', '.join(run_control.ACTIONS)}")
    prompt = value.get("prompt")
    if action == "answer":
        if isinstance(prompt, float) and math.isfinite(prompt) and prompt.is_integer():
            prompt = int(prompt)
        if not isinstance(prompt, int) or isinstance(prompt, bool) or not 0 <= prompt < 2**53:
            raise ValueError("prompt must be the whole number of the question shown")
    yes = value.get("yes", False)
    if not isinstance(yes, bool):
        raise ValueError("yes must be true or false")
    return {"action": action, "prompt": prompt if action == "answer" else None, "yes": yes}


def file_chunks(fh: BinaryIO) -> Iterator[bytes]:
    """The content of the open file ``fh`` in chunks; closes it at the end (a response never
    sent leaves it to the garbage collector, which closes it too)."""
    with fh:
        while chunk := fh.read(CHUNK):
            yield chunk


class PageUndefined(jinja2.Undefined):
    """A name a template prints or loops over that the page does not give is an error (a 500
    naming it), never an empty cell; testing it (``{% if error %}``) is false, as the templates
    test the names a page gives only sometimes."""

    __slots__ = ()
    __str__ = __iter__ = __len__ = jinja2.Undefined._fail_with_undefined_error


class Site:
    """The state one server shares between its requests."""

    def __init__(self, runs_dir: Path, rig_config: Path | None, csrf_secret: str,
                 lab_url: str | None = None) -> None:  # fmt: skip
        self.runs_dir = runs_dir
        self.rig_config = rig_config
        self.csrf_secret = csrf_secret
        self.lab_url = lab_url
        self.templates = Jinja2Templates(directory=str(HERE / "templates"))
        self.templates.env.undefined = PageUndefined
        self.templates.env.filters["seg"] = segment

    def page(self, request: Request, name: str, status: int = 200, **context: Any) -> Response:
        return self.templates.TemplateResponse(
            request,
            name,
            {"csrf": self.csrf_secret, "lab": self.lab_url is not None, **context},
            status_code=status,
        )

    def folder(self, request: Request) -> Path | None:
        return run_folder(self.runs_dir, request.path_params["run_id"])


async def runs_page(site: Site, request: Request) -> Response:
    return site.page(request, "runs.html", runs=list_summaries(site.runs_dir),
                     runs_dir=str(site.runs_dir))  # fmt: skip


async def runs_api(site: Site, request: Request) -> Response:
    rows = [r.to_dict() for r in list_summaries(site.runs_dir)]
    q = request.query_params.get("q", "").strip().lower()
    if q:
        rows = [r for r in rows if any(q in str(v).lower() for v in r.values())]
    return JSONResponse(rows)


async def run_page(site: Site, request: Request) -> Response:
    folder = site.folder(request)
    run_id = request.path_params["run_id"]
    if folder is None:
        return site.page(request, "message.html", 404, title=f"No run {run_id}",
                         message="no such run in this runs folder")  # fmt: skip
    try:
        details = run_details(folder)
    except Exception as exc:  # a damaged store: say so in one line, the list still works
        return site.page(request, "message.html", 500, title=f"Run {run_id} is {DAMAGED}",
                         message=damage(exc))  # fmt: skip
    return site.page(request, "run.html", run=details)


async def run_api(site: Site, request: Request) -> Response:
    folder = site.folder(request)
    if folder is None:
        return JSONResponse({"error": "no such run"}, status_code=404)
    try:
        return JSONResponse(run_details(folder))
    except Exception as exc:
        return JSONResponse({"error": damage(exc), "status": DAMAGED}, status_code=500)


async def run_file(site: Site, request: Request) -> Response:
    folder = site.folder(request)
    name = request.path_params["name"]
    if folder is None or name not in downloads(folder):
        return text(404, "no such file in this run")
    try:  # opened without following a link, a regular file only (checked again on the fd)
        fd = safe_files.open_fd(folder / name)
    except (OSError, safe_files.UnsafeFileError):
        return text(404, "no such file in this run")
    headers = {"content-length": str(os.fstat(fd).st_size)}
    if name in FRAMED_FILES:
        headers |= {"content-security-policy": FRAMED_FILE_CSP,
                    "x-frame-options": "SAMEORIGIN"}  # fmt: skip
    if not name.endswith((".png", ".html")):
        headers["content-disposition"] = f"attachment; filename*=utf-8''{quote(name)}"
    return StreamingResponse(file_chunks(os.fdopen(fd, "rb")), media_type=media_type(name),
                             headers=headers)  # fmt: skip


async def run_export(site: Site, request: Request) -> Response:
    folder = site.folder(request)
    fmt = request.path_params["fmt"]
    if folder is None or fmt not in EXPORTS:
        return text(404, "no such run or export format")
    summary = summary_or_damaged(folder)
    if summary.status == DAMAGED:
        return text(500, f"run {folder.name} is {DAMAGED}: {summary.reason}")
    if summary.status == "running":
        return text(409, "the run is still recording; export it once it has ended")
    tmp = tempfile.mkdtemp(prefix="rig-export-")
    path, name, media = await asyncio.to_thread(export_file, folder, fmt, Path(tmp))
    return FileResponse(path, media_type=media, filename=name,
                        background=BackgroundTask(shutil.rmtree, tmp, True))  # fmt: skip


async def live_stream(site: Site, request: Request) -> Response:
    folder = site.folder(request)
    if folder is None:
        return text(404, "no such run")

    async def events() -> AsyncIterator[str]:
        last = None
        while not await request.is_disconnected():
            state = read_live(folder)
            if state is not None and state != last:
                last = state
                yield f"data: {json.dumps(state, separators=(',', ':'))}\n\n"
                if state.get("status", "running") != "running":
                    return  # the run has ended: its final state was the last word
            await asyncio.sleep(LIVE_POLL_S)

    return StreamingResponse(events(), media_type="text/event-stream",
                             headers={"cache-control": "no-store"})  # fmt: skip


async def control(site: Site, request: Request) -> Response:
    folder = site.folder(request)
    if folder is None:
        return JSONResponse({"error": "no such run"}, status_code=404)
    summary = summary_or_damaged(folder)
    if summary.status == DAMAGED:
        return JSONResponse({"error": f"the run is {DAMAGED}: {summary.reason}"},
                            status_code=500)  # fmt: skip
    if summary.status != "running":
        return JSONResponse({"error": "the run has ended"}, status_code=409)
    body = await request.body()  # the guard refused one over security.MAX_BODY bytes
    try:
        req = parse_control(body)
    except ValueError as exc:
        return bad_request(f"bad control request: {exc}")
    try:
        run_control.request(folder, req["action"], prompt=req["prompt"], yes=req["yes"])
    except RigError as exc:
        return JSONResponse({"error": str(exc)}, status_code=409)
    return JSONResponse({"queued": req["action"]})


async def cage_page(site: Site, request: Request) -> Response:
    return site.page(request, "cage.html", cage=cage_status(site.rig_config),
                     running=[r for r in list_summaries(site.runs_dir)
                              if r.status == "running"])  # fmt: skip


async def lab_page(site: Site, request: Request) -> Response:
    """/lab (runs), /lab/dut/SERIAL, /lab/<view>: the views of :data:`rig.web.lab_views.VIEWS`."""
    if site.lab_url is None:
        return site.page(request, "lab.html", 404, view=None)
    from rig.web.lab_views import VIEWS, tabs

    name = "dut" if "serial" in request.path_params else request.path_params.get("view", "runs")
    view = VIEWS.get(name)
    if view is None:
        return site.page(request, "lab.html", 404, view=None)
    query = dict(request.query_params)
    try:
        data = await asyncio.to_thread(view.load, site.lab_url, query | request.path_params)
    except RigError as exc:  # the index is down or refused: say so, the runs stay local
        return site.page(request, "lab.html", 503, view=name, tabs=tabs(), error=str(exc))
    return site.page(request, "lab.html", view=name, tabs=tabs(), data=data, query=query)


async def lab_trend_png(site: Site, request: Request) -> Response:
    if site.lab_url is None or not request.query_params.get("param"):
        return text(404, "no lab index or no param")
    from rig.web.lab_views.trend import lab_trend

    tmp = Path(tempfile.mkdtemp(prefix="rig-trend-"))
    png = tmp / "trend.png"
    try:
        data = await asyncio.to_thread(lab_trend, site.lab_url,
                                       request.query_params["param"],
                                       request.query_params.get("lot"), png)  # fmt: skip
    except RigError as exc:
        shutil.rmtree(tmp, True)
        return text(503, str(exc))
    if not data["found"]:
        shutil.rmtree(tmp, True)
        return text(404, "no values")
    return FileResponse(png, media_type="image/png",
                        background=BackgroundTask(shutil.rmtree, tmp, True))  # fmt: skip


ROUTES: tuple[tuple[str, Callable[[Site, Request], Awaitable[Response]], str], ...] = (
    ("/", runs_page, "GET"),
    ("/api/runs", runs_api, "GET"),
    ("/runs/{run_id}", run_page, "GET"),
    ("/api/runs/{run_id}", run_api, "GET"),
    ("/runs/{run_id}/files/{name}", run_file, "GET"),
    ("/runs/{run_id}/export/{fmt}", run_export, "GET"),
    ("/runs/{run_id}/live", live_stream, "GET"),
    ("/runs/{run_id}/control", control, "POST"),
    ("/cage", cage_page, "GET"),
    ("/lab", lab_page, "GET"),
    ("/lab/trend.png", lab_trend_png, "GET"),
    ("/lab/dut/{serial:path}", lab_page, "GET"),
    ("/lab/{view}", lab_page, "GET"),
)
"""Every route: path, handler (given the site and the request) and method, in match order."""


def routes(site: Site) -> list[BaseRoute]:
    """The application's routes for ``site``, and its static files."""
    return [
        *(
            Route(path, partial(handler, site), methods=[method])
            for path, handler, method in ROUTES
        ),
        Mount("/static", StaticFiles(directory=str(HERE / "static")), name="static"),
    ]


def create_app(runs_dir: Path, rig_config: Path | None = None, *, access_token: str,
               loopback_only: bool = True, csrf_secret: str | None = None,
               lab_url: str | None = None, token_hint: str = "") -> Guard:  # fmt: skip
    """The application for ``runs_dir`` (the cage of ``rig_config``, the lab index at
    ``lab_url``), wrapped in its guard: every request needs ``access_token`` (``token_hint``:
    where its owner finds it)."""
    site = Site(runs_dir, rig_config, csrf_secret or new_secret(), lab_url)

    app = Starlette(routes=routes(site), exception_handlers={Exception: internal_error})
    return Guard(app, csrf_secret=site.csrf_secret, access_token=access_token,
                 loopback_only=loopback_only, token_hint=token_hint)  # fmt: skip


async def internal_error(request: Request, exc: Exception) -> Response:
    """Any error no route expected: 500 with one line naming it (never a traceback)."""
    line = " ".join(str(exc).split())[:300] or "no detail"
    return text(500, f"internal error: {type(exc).__name__}: {line}; the server's log has more")


def cage_status(rig_config: Path | None) -> dict[str, Any] | None:
    """The cage page: devices with their roles, limits and the cage calibration's age."""
    if rig_config is None:
        return None
    from rig.config import load_rig_config

    try:
        cfg = load_rig_config(rig_config)
    except RigError as exc:
        return {"error": str(exc), "path": str(rig_config)}
    out: dict[str, Any] = {"path": str(rig_config), "devices": [
        {"name": d.name, "kind": d.kind, "protocol": d.protocol,
         "where": d.where}
        for d in cfg.devices.values()]}  # fmt: skip
    cage = cfg.cage
    if cage is not None:
        out["limits"] = {
            "max_current_a": list(cage.max_current_a),
            "max_field_ut": cage.max_field_ut,
            "max_slew_a_per_s": cage.max_slew_a_per_s,
            "compliance_v": cage.compliance_v,
        }
        out["axes"] = list(cage.axes)
        out["reference"] = cage.reference
        out["polarity"] = cage.polarity
        cal = cage.calibration
        if cal is not None and cal.exists():
            age = dt.datetime.now(dt.UTC) - dt.datetime.fromtimestamp(cal.stat().st_mtime, dt.UTC)
            out["calibration"] = {
                "path": str(cal),
                "age_days": round(age.total_seconds() / 86400, 1),
            }
        else:
            out["calibration"] = {"path": str(cal) if cal else None, "age_days": None}
    return out
