"""Who may talk to ``rig serve``: the run's owner only, from the page itself, never in a frame.

- Host: on loopback only ``localhost``, ``127.0.0.1`` and ``[::1]`` are accepted as the Host header
  (a page on another site cannot reach the server through a DNS name that points at 127.0.0.1).
- Token: every server, on loopback too, has a random access token. It is printed in the address
  (``http://127.0.0.1:8765/?token=...``) and written to a file only the owner can read
  (:func:`write_access_file`); the first request with ``?token=`` gets it as an HttpOnly,
  SameSite=Strict cookie and is redirected to the address without it. Every request needs the
  cookie (or ``Authorization: Bearer TOKEN``, for the owner's scripts): another local account can
  connect to a loopback port, but it cannot read the token, so it sees no page and no CSRF secret.
- Cross-site requests: every state-changing request (POST) needs the header ``X-Rig-CSRF`` with the
  server's secret, which only its own pages carry; browsers do not let another site set that
  header without a CORS preflight, which this server never grants. An ``Origin`` that is not the
  server's own is refused as well.
- Framing: every response says ``frame-ancestors 'none'`` (CSP) and ``X-Frame-Options: DENY``, so no
  other page (another site, another loopback address or port) can frame the run page and lure a
  click on Abort; a run's report, framed by the run page itself, says ``'self'`` and runs no
  script.
- Bodies: a request body longer than :data:`MAX_BODY` is refused with 413 before it is read (by
  its Content-Length, or by counting as it streams in).
"""

from __future__ import annotations

import contextlib
import hmac
import os
import secrets
import stat
from collections.abc import Awaitable, Callable, MutableMapping
from http.cookies import SimpleCookie
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlencode

from rig.errors import UserInputError
from rig.store import safe_files

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "[::1]", "::1")
TOKEN_COOKIE = "rig_token"
"""The cookie's name, followed by the server's port: cookies do not tell ports apart, and two
servers of one owner (``rig serve``, ``rig run --serve``) must not overwrite each other's."""
CSRF_HEADER = "x-rig-csrf"
MAX_BODY = 64 * 1024
"""The largest request body accepted (bytes); a prompt answer or a control request is < 100."""
PAGE_CSP = ("default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline';"
            " img-src 'self' data:; object-src 'none'; base-uri 'none'; form-action 'self';"
            " frame-ancestors 'none'")  # fmt: skip
"""The pages' policy: their own scripts only (no inline script), framed by nobody."""
FRAMED_FILE_CSP = ("default-src 'none'; img-src 'self' data:; style-src 'unsafe-inline';"
                   " base-uri 'none'; form-action 'none'; frame-ancestors 'self'")  # fmt: skip
"""A run folder's HTML report: no script runs in it (an edited report cannot reach the page's
secret), and only the run page itself may frame it."""
SECURITY_HEADERS = [(b"x-content-type-options", b"nosniff"), (b"referrer-policy", b"no-referrer")]


def new_secret() -> str:
    """A random secret (URL safe, 256 bits)."""
    return secrets.token_urlsafe(32)


def access_dir() -> Path:
    """The owner's private folder for access files: ``$XDG_RUNTIME_DIR/rig-serve``, else
    ``~/.cache/rig-serve``."""
    base = os.environ.get("XDG_RUNTIME_DIR") or str(Path.home() / ".cache")
    return Path(base) / "rig-serve"


def access_file_path(port: int) -> Path:
    """Where the server on ``port`` keeps its access address: ``access_dir()/PORT.url``."""
    return access_dir() / f"{port}.url"


def write_access_file(url: str, port: int) -> Path:
    """Write the access address ``url`` (with its token) to :func:`access_file_path`, readable by
    this account only (0600 in a 0700 folder it owns); returns the path."""
    path = access_file_path(port)
    folder = path.parent
    folder.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    with contextlib.suppress(FileExistsError):
        os.mkdir(folder, 0o700)
    st = os.lstat(folder)
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.geteuid():
        raise UserInputError(f"{folder}: not a folder of this account (uid {st.st_uid}); remove"
                             " it, or set XDG_RUNTIME_DIR to a private folder")  # fmt: skip
    if stat.S_IMODE(st.st_mode) & 0o077:
        os.chmod(folder, 0o700)
    safe_files.write_text(path, url + "\n", mode=0o600)
    return path


def _host_name(host_header: str) -> str:
    if host_header.startswith("["):
        return host_header.split("]")[0] + "]"
    return host_header.rsplit(":", 1)[0] if ":" in host_header else host_header


class BodyTooLargeError(Exception):
    """A request body went past :data:`MAX_BODY` while it streamed in."""


class Guard:
    """ASGI middleware applying the rules above to every HTTP request."""

    def __init__(self, app: ASGIApp, *, csrf_secret: str, access_token: str, loopback_only: bool,
                 token_hint: str = "") -> None:  # fmt: skip
        self.app = app
        self.csrf_secret = csrf_secret
        self.access_token = access_token
        self.loopback_only = loopback_only
        self.token_hint = token_hint

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        send = _with_security_headers(send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        host = headers.get("host", "")
        if self.loopback_only and _host_name(host) not in LOOPBACK_HOSTS:
            await refuse(send, 421, f"this server answers on localhost only, not {host!r}")
            return
        if not await self._token_ok(scope, headers, send):
            return
        if scope["method"] not in ("GET", "HEAD", "OPTIONS"):
            origin = headers.get("origin")
            if origin is not None and origin.split("://", 1)[-1] != host:
                await refuse(send, 403, "cross-site request refused")
                return
            if not hmac.compare_digest(headers.get(CSRF_HEADER, ""), self.csrf_secret):
                await refuse(send, 403, "missing or wrong X-Rig-CSRF header: use the rig page")
                return
        length = headers.get("content-length", "0")
        if not length.isdigit() or int(length) > MAX_BODY:
            await refuse(send, 413, f"request body over {MAX_BODY} bytes refused")
            return
        try:
            body = await _read_body(receive)
        except BodyTooLargeError:
            await refuse(send, 413, f"request body over {MAX_BODY} bytes refused")
            return
        await self.app(scope, _replay(body, receive), send)

    def _cookie_name(self, scope: Scope) -> str:
        server = scope.get("server") or ("", 0)
        return f"{TOKEN_COOKIE}_{server[1]}"

    async def _token_ok(self, scope: Scope, headers: dict[str, str], send: Send) -> bool:
        name = self._cookie_name(scope)
        cookie: SimpleCookie = SimpleCookie()
        with contextlib.suppress(Exception):  # a malformed cookie header counts as none
            cookie.load(headers.get("cookie", ""))
        sent = cookie[name].value if name in cookie else ""
        bearer = headers.get("authorization", "")
        bearer = bearer[7:] if bearer[:7].lower() == "bearer " else ""
        if hmac.compare_digest(sent, self.access_token) or (
            bearer and hmac.compare_digest(bearer, self.access_token)
        ):
            return True
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        given = query.pop("token", [""])[0]
        if given and hmac.compare_digest(given, self.access_token):
            if scope["method"] not in ("GET", "HEAD"):
                return True
            rest = urlencode(query, doseq=True)
            location = (scope.get("raw_path") or scope["path"].encode()).decode("latin-1")
            location = location + (f"?{rest}" if rest else "")
            await send({"type": "http.response.start", "status": 303, "headers": [
                (b"location", location.encode("latin-1")),
                (b"set-cookie", f"{name}={self.access_token}; HttpOnly; SameSite=Strict;"
                                f" Path=/".encode("latin-1")),
                (b"content-length", b"0"),
            ]})  # fmt: skip
            await send({"type": "http.response.body", "body": b""})
            return False
        hint = f", or read it from {self.token_hint}" if self.token_hint else ""
        await refuse(send, 401, "this page needs its access token: open the address 'rig serve'"
                                f" printed (it carries ?token=){hint}")  # fmt: skip
        return False


def _with_security_headers(send: Send) -> Send:
    """``send`` adding the framing, sniffing and policy headers to every response (a response that
    sets its own CSP or X-Frame-Options keeps them)."""

    async def wrapped(message: Message) -> None:
        if message["type"] == "http.response.start":
            headers = list(message.get("headers", []))
            names = {k.lower() for k, _ in headers}
            if b"content-security-policy" not in names:
                headers.append((b"content-security-policy", PAGE_CSP.encode()))
            if b"x-frame-options" not in names:
                headers.append((b"x-frame-options", b"DENY"))
            headers += [h for h in SECURITY_HEADERS if h[0] not in names]
            message = {**message, "headers": headers}
        await send(message)

    return wrapped


async def _read_body(receive: Receive) -> bytes:
    """The whole request body, counted as it comes (BodyTooLargeError past :data:`MAX_BODY`)."""
    chunks: list[bytes] = []
    size = 0
    while True:
        message = await receive()
        if message["type"] != "http.request":
            break  # the client went away; the app sees an empty body
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > MAX_BODY:
            raise BodyTooLargeError
        chunks.append(chunk)
        if not message.get("more_body", False):
            break
    return b"".join(chunks)


def _replay(body: bytes, receive: Receive) -> Receive:
    """A ``receive`` that gives ``body`` once, then whatever the server says (a disconnect)."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


async def refuse(send: Send, status: int, text: str) -> None:
    """Answer ``status`` with one line of plain text."""
    body = (text + "\n").encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"),
                            (b"content-length", str(len(body)).encode())]})  # fmt: skip
    await send({"type": "http.response.body", "body": body})
