"""API keys: who is calling.

Keys come from ``PWLREG_API_KEYS`` and ``PWLREG_API_KEYS_FILE`` (:class:`~service.settings.
Settings`). Without any key the service is open and every caller is the anonymous client
(``None``); with keys, every endpoint that depends on :data:`ClientDep` needs
``Authorization: Bearer <key>`` and yields the name of the key's client, the owner of the jobs
it submits. Keys are compared in constant time and never logged.
"""

from __future__ import annotations

import hashlib
import hmac
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from pwlreg.service.deps import ServicesDep
from pwlreg.service.problems import Problem
from pwlreg.service.settings import Settings

_NAME = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
_KEY = re.compile(r"^[A-Za-z0-9._~+/-]+=*$")  # RFC 6750 b64token: fits a Bearer header


class ApiKeys:
    """The configured keys, by client name.

    Parameters
    ----------
    keys : iterable of (name, key)
        Client names (unique) and their keys (unique).
    """

    def __init__(self, keys: Iterable[tuple[str, str]] = ()) -> None:
        self._digests: list[tuple[str, bytes]] = []
        names: set[str] = set()
        digests: set[bytes] = set()
        for name, key in keys:
            digest = _digest(key)
            if name in names:
                raise ValueError(f"API key client name {name!r} given twice")
            if digest in digests:
                raise ValueError(f"the API key of client {name!r} is also another client's key")
            names.add(name)
            digests.add(digest)
            self._digests.append((name, digest))

    def __bool__(self) -> bool:
        return bool(self._digests)

    def __len__(self) -> int:
        return len(self._digests)

    @property
    def names(self) -> list[str]:
        return [name for name, _ in self._digests]

    def identify(self, key: str) -> str | None:
        """The client name of ``key``, or None. Every configured key is compared (in constant
        time, over SHA-256 digests so that the lengths do not show), even after a match."""
        given = _digest(key)
        found: str | None = None
        for name, digest in self._digests:
            if hmac.compare_digest(given, digest):
                found = name
        return found


def _digest(key: str) -> bytes:
    return hashlib.sha256(key.encode("utf-8", "surrogateescape")).digest()


def _check(name: str, key: str, where: str) -> tuple[str, str]:
    # Messages name the client and the place, never the key.
    if not _NAME.match(name):
        raise ValueError(
            f"{where}: client name {name!r} must be 1-64 letters, digits, '.', '_' or '-'"
        )
    if not _KEY.match(key):
        raise ValueError(
            f"{where}: the key of client {name!r} must be letters, digits and -._~+/ "
            "(optionally ending with '='), to fit an Authorization: Bearer header"
        )
    return name, key


def parse_keys(value: str) -> list[tuple[str, str]]:
    """Entries of ``PWLREG_API_KEYS``: comma-separated ``name:key`` or bare ``key`` (named
    ``client1``, ``client2``, ... in the order of the bare keys)."""
    keys = []
    bare = 0
    for i, entry in enumerate(value.split(","), start=1):
        entry = entry.strip()
        if not entry:
            continue
        if ":" in entry:
            name, key = (part.strip() for part in entry.split(":", 1))
        else:
            bare += 1
            name, key = f"client{bare}", entry
        keys.append(_check(name, key, f"PWLREG_API_KEYS entry {i}"))
    return keys


def read_keys_file(path: Path) -> list[tuple[str, str]]:
    """Lines ``name key`` of a keys file; ``#`` starts a comment, blank lines are skipped."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ValueError(f"PWLREG_API_KEYS_FILE {path}: cannot read it ({exc.strerror})") from None
    keys = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.split()
        where = f"PWLREG_API_KEYS_FILE {path} line {number}"
        if len(fields) != 2:
            raise ValueError(f"{where}: expected 'name key', got {len(fields)} field(s)")
        keys.append(_check(fields[0], fields[1], where))
    return keys


def load_api_keys(settings: Settings) -> ApiKeys:
    """Every key of the settings (``api_keys`` then ``api_keys_file``); ValueError, naming the
    entry but not the key, if one is malformed or a name or key is repeated."""
    keys = parse_keys(settings.api_keys.get_secret_value() if settings.api_keys else "")
    if settings.api_keys_file is not None:
        keys += read_keys_file(settings.api_keys_file)
    return ApiKeys(keys)


# --- the dependency ----------------------------------------------------------------------------

bearer = HTTPBearer(
    scheme_name="apiKey",
    description="API key of the client, sent as `Authorization: Bearer <key>`. Needed only "
    "when the server has keys configured (PWLREG_API_KEYS, PWLREG_API_KEYS_FILE).",
    auto_error=False,
)


def unauthorized(detail: str) -> Problem:
    return Problem(
        401, "unauthorized", "Unauthorized", detail, "Authorization",
        headers={"WWW-Authenticate": "Bearer"},
    )


def get_client(
    request: Request,
    services: ServicesDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> str | None:
    """The name of the calling client; None when the server has no keys (open access).

    The name is also kept in ``request.state.client`` (read by the middleware that counts
    refused submissions).

    Raises
    ------
    Problem
        401 with ``WWW-Authenticate: Bearer`` when keys are configured and the request has no
        ``Authorization: Bearer <key>`` header, a malformed one, or an unknown key.
    """
    keys = services.api_keys
    if not keys:
        return None
    if credentials is None:
        raise unauthorized("this server needs an API key: send 'Authorization: Bearer <key>'")
    client = keys.identify(credentials.credentials)
    if client is None:
        raise unauthorized("unknown API key")
    request.state.client = client  # for the metrics of the answer (service.metrics)
    return client


ClientDep = Annotated[str | None, Depends(get_client)]
"""The calling client's name (None without configured keys)."""
