"""``rig serve``: the local web page for live runs, past runs and the cage (``rig.web``).

Every server has an access token (on loopback too: any local account can connect to a loopback
port). The address printed carries it, and so does a file only this account can read
(``rig.web.security.write_access_file``), removed when the server ends.
"""

from __future__ import annotations

import argparse
import contextlib
import ipaddress
import os
import signal
import socket
import sys
from pathlib import Path

from rig.cli.common import Parser, Subparsers
from rig.errors import RigError, UserInputError

DEFAULT_PORT = 8765


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    p = sub.add_parser(
        "serve", parents=parents, help="serve the web page: live runs, past runs, cage"
    )
    p.add_argument("--runs-dir", type=Path, default=Path("runs"), metavar="DIR",
                   help="the runs to show and operate (default: runs)")  # fmt: skip
    p.add_argument("--rig", type=Path, metavar="CONFIG.toml",
                   help="rig configuration, for the cage status page")  # fmt: skip
    p.add_argument("--port", type=int, default=DEFAULT_PORT, metavar="N",
                   help=f"TCP port (default {DEFAULT_PORT}; 0 picks a free one)")  # fmt: skip
    p.add_argument("--host", default="127.0.0.1", metavar="ADDR",
                   help="address to listen on (default 127.0.0.1, this machine only)")  # fmt: skip
    p.add_argument("--lab", metavar="URL", default=None,
                   help="lab index to show on the Lab page: postgresql://USER@HOST:PORT/DB"
                        " (default: $RIG_LAB_URL, else [lab] url of --rig; none: no Lab page)")  # fmt: skip
    p.add_argument("--allow-remote", action="store_true",
                   help="allow an address other than loopback (anyone with the address and its"
                        " token can operate the rig)")  # fmt: skip
    p.set_defaults(func=_cmd_serve)


def _cmd_serve(args: argparse.Namespace) -> int:
    return serve(args.runs_dir, args.rig, args.host, args.port, args.allow_remote, args.quiet,
                 lab=args.lab)  # fmt: skip


def is_loopback(host: str) -> bool:
    """``host`` names this machine only (127.0.0.0/8, ::1 or localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def listen(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (raises UserInputError naming the fix)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise UserInputError(f"cannot listen on {host}:{port} ({exc.strerror}); choose another"
                             " --port, or 0 for a free one") from None  # fmt: skip
    sock.listen(64)
    return sock


def serve(runs_dir: Path, rig_config: Path | None, host: str, port: int, allow_remote: bool,
          quiet: bool, lab: str | None = None) -> int:  # fmt: skip
    """Serve until Ctrl-C or SIGTERM; prints the address with its access token first."""
    import uvicorn

    from rig.web.app import create_app
    from rig.web.security import access_file_path, new_secret, write_access_file

    loopback = is_loopback(host)
    if not loopback and not allow_remote:
        raise UserInputError(f"--host {host} is reachable from other machines; add --allow-remote"
                             " to serve it there (with an access token), or drop --host")  # fmt: skip
    if rig_config is not None and not rig_config.is_file():
        raise UserInputError(f"{rig_config}: no such rig configuration; check --rig")
    lab_url = _lab_url(lab, rig_config)
    token = new_secret()
    sock = listen(host, port)
    shown = f"[{host}]" if ":" in host else host
    bound = sock.getsockname()[1]
    url = f"http://{shown}:{bound}/?token={token}"
    # before the file exists: a SIGTERM from here on removes it (from the printed address on, a
    # caller may stop us at once, while the page is still being built)
    _remove_on_sigterm(access_file_path(bound))
    try:
        access_file = write_access_file(url, bound)
    except (OSError, RigError) as exc:
        sock.close()
        raise UserInputError(f"cannot write the page's access file ({exc}); set XDG_RUNTIME_DIR"
                             " to a folder of yours") from None  # fmt: skip
    try:
        print(f"rig serve: {url}", flush=True)
        if not quiet:
            who = "anyone with it" if not loopback else "this account only (keep it to yourself)"
            print(f"rig serve: the address carries the page's access token, also in {access_file};"
                  f" {who} can operate the rig", file=sys.stderr, flush=True)  # fmt: skip
        app = create_app(runs_dir, rig_config, access_token=token, loopback_only=loopback,
                         lab_url=lab_url, token_hint=str(access_file))  # fmt: skip
        config = uvicorn.Config(app, log_level="warning" if not quiet else "error",
                                access_log=False, lifespan="off",
                                timeout_graceful_shutdown=1)  # fmt: skip
        server = uvicorn.Server(config)
        server.run(sockets=[sock])
    finally:
        with contextlib.suppress(OSError):
            access_file.unlink()
    return 0


def _remove_on_sigterm(path: Path) -> None:
    """On SIGTERM remove ``path``, then end as SIGTERM does (uvicorn shuts down first, then
    raises the signal again to the handler it found: this one)."""

    def on_term(signum: int, frame: object) -> None:
        with contextlib.suppress(OSError):
            path.unlink()
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)

    signal.signal(signal.SIGTERM, on_term)


def _lab_url(arg: str | None, rig_config: Path | None) -> str | None:
    """The lab index for the Lab page (``--lab``, ``RIG_LAB_URL``, ``[lab] url``), or None."""
    from rig.lab.url import resolve_url

    raw = None
    if rig_config is not None:
        from rig.config import load_rig_config

        raw = load_rig_config(rig_config).raw
    return resolve_url(arg, raw, rig_config or "")
