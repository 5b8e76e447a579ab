"""Where the lab index is: ``--lab URL``, else ``RIG_LAB_URL``, else ``[lab] url`` of the rig
configuration. Passwords never live in the rig configuration (it is copied into every run folder)
and are never printed: :func:`masked` hides one in any URL a message shows.
"""

from __future__ import annotations

import os
import re
from typing import Any
from urllib.parse import unquote, urlsplit

from rig.errors import UserInputError

ENV_VAR = "RIG_LAB_URL"
SCHEMES = ("postgresql", "postgres")
_PASSWORD_IN_NETLOC = re.compile(r"(//[^/@:]*:)([^@/]*)(@)")
_PASSWORD_IN_QUERY = re.compile(r"(password=)([^&\s]*)", re.IGNORECASE)
_QUERY_PAIR = re.compile(r"([?&])([^=&#\s]*)=([^&#\s]*)")


def _mask_query(match: re.Match[str]) -> str:
    """A ``key=value`` pair of the query with the value hidden when the key, percent-decoded
    (libpq decodes it: ``pass%77ord`` is ``password``), names the password."""
    sep, key, _value = match.groups()
    return f"{sep}{key}=***" if unquote(key).strip().lower() == "password" else match.group(0)


def masked(url: str) -> str:
    """The URL with any password replaced by ``***`` (user, host, port and database kept)."""
    url = _PASSWORD_IN_QUERY.sub(r"\1***", _PASSWORD_IN_NETLOC.sub(r"\1***\3", url))
    return _QUERY_PAIR.sub(_mask_query, url)


def has_password(url: str) -> bool:
    """True when the URL carries a password (``user:pw@host``, or ``?password=`` with the key
    spelled in any case or percent-encoding)."""
    return masked(url) != url


def check_url(url: str, where: str) -> str:
    """A PostgreSQL URL, or a one-line error naming ``where`` it came from."""
    if urlsplit(url).scheme not in SCHEMES:
        raise UserInputError(
            f"{where}: {masked(url)!r} is not a PostgreSQL URL; write"
            " postgresql://USER@HOST:PORT/DATABASE (see docs/lab.md)"
        )
    return url


def config_url(raw: dict[str, Any], path: object) -> str | None:
    """``[lab] url`` of a parsed rig configuration, checked: no password in it. The ``[lab]`` keys
    are declared in :data:`rig.config.LAB_KEYS` (unknown ones are refused when the file loads)."""
    lab = raw.get("lab")
    if lab is None:
        return None
    if not isinstance(lab, dict):
        raise UserInputError(f'{path}: [lab] must be a table (url = "postgresql://...")')
    url = lab.get("url")
    if url is None:
        return None
    if not isinstance(url, str):
        raise UserInputError(f"{path}: [lab].url must be a string postgresql://USER@HOST/DB")
    if has_password(url):
        raise UserInputError(
            f"{path}: [lab].url holds a password, and the rig configuration is copied into every"
            " run folder: remove it and put it in ~/.pgpass (or PGPASSWORD); see docs/lab.md"
        )
    return check_url(url, f"{path}: [lab].url")


def rig_name(raw: dict[str, Any]) -> str | None:
    """``[lab] rig``: this rig's name in the index (else the host name is used)."""
    lab = raw.get("lab")
    name = lab.get("rig") if isinstance(lab, dict) else None
    return str(name) if name else None


def resolve_url(
    arg: str | None, raw: dict[str, Any] | None = None, path: object = ""
) -> str | None:
    """The lab index URL: ``--lab``, else ``RIG_LAB_URL``, else the configuration; None if none."""
    if arg:
        return check_url(arg, "--lab")
    env = os.environ.get(ENV_VAR)
    if env:
        return check_url(env, ENV_VAR)
    return config_url(raw, path) if raw is not None else None
