"""Who may talk to ``rig serve``: loopback by default, a token for anything else, no cross-site writes.

- Host: on loopback only ``localhost``, ``127.0.0.1`` and ``[::1]`` are accepted as the Host header
  (a page on another site cannot reach the server through a DNS name that points at 127.0.0.1).
- Token: a server bound to another address prints a one-time access URL with a random token; the
  first request with ``?token=`` sets a cookie and every request needs it.
- Cross-site requests: every state-changing request (POST) needs the header ``X-Rig-CSRF`` with the
  server's secret, which only its own pages carry; browsers do not let another site set that
  header without a CORS preflight, which this server never grants. An ``Origin`` that is not the
  server's own is refused as well.
"""

from __future__ import annotations

import hmac
import secrets
from collections.abc import Awaitable, Callable, MutableMapping
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs, urlencode

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "[::1]", "::1")
TOKEN_COOKIE = "rig_token"
CSRF_HEADER = "x-rig-csrf"


def new_secret() -> str:
    """A random secret (URL safe, 256 bits)."""
    return secrets.token_urlsafe(32)


def _host_name(host_header: str) -> str:
    if host_header.startswith("["):
        return host_header.split("]")[0] + "]"
    return host_header.rsplit(":", 1)[0] if ":" in host_header else host_header


class Guard:
    """ASGI middleware applying the three rules above to every HTTP request."""

    def __init__(self, app: ASGIApp, *, csrf_secret: str, access_token: str | None,
                 loopback_only: bool) -> None:  # fmt: skip
        self.app = app
        self.csrf_secret = csrf_secret
        self.access_token = access_token
        self.loopback_only = loopback_only

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        host = headers.get("host", "")
        if self.loopback_only and _host_name(host) not in LOOPBACK_HOSTS:
            await _refuse(send, 421, f"this server answers on localhost only, not {host!r}")
            return
        if self.access_token is not None and not await self._token_ok(scope, headers, send):
            return
        if scope["method"] not in ("GET", "HEAD", "OPTIONS"):
            origin = headers.get("origin")
            if origin is not None and origin.split("://", 1)[-1] != host:
                await _refuse(send, 403, "cross-site request refused")
                return
            if not hmac.compare_digest(headers.get(CSRF_HEADER, ""), self.csrf_secret):
                await _refuse(send, 403, "missing or wrong X-Rig-CSRF header: use the rig page")
                return
        await self.app(scope, receive, send)

    async def _token_ok(self, scope: Scope, headers: dict[str, str], send: Send) -> bool:
        assert self.access_token is not None
        cookie = SimpleCookie(headers.get("cookie", ""))
        sent = cookie[TOKEN_COOKIE].value if TOKEN_COOKIE in cookie else ""
        if hmac.compare_digest(sent, self.access_token):
            return True
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        given = query.pop("token", [""])[0]
        if given and hmac.compare_digest(given, self.access_token):
            rest = urlencode(query, doseq=True)
            location = scope["path"] + (f"?{rest}" if rest else "")
            await send({"type": "http.response.start", "status": 303, "headers": [
                (b"location", location.encode("latin-1")),
                (b"set-cookie", f"{TOKEN_COOKIE}={self.access_token}; HttpOnly; SameSite=Strict;"
                                f" Path=/".encode("latin-1")),
            ]})  # fmt: skip
            await send({"type": "http.response.body", "body": b""})
            return False
        await _refuse(send, 401, "open the access URL 'rig serve' printed (it carries the token)")
        return False


async def _refuse(send: Send, status: int, text: str) -> None:
    body = (text + "\n").encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"),
                            (b"content-length", str(len(body)).encode())]})  # fmt: skip
    await send({"type": "http.response.body", "body": body})
