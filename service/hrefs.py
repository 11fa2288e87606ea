"""Inputs given by reference: the service reads an ``href`` of an OGC execute request.

Reading a URL on a client's behalf is a server-side request forgery risk, so only origins on
the operator's list (``PWLREG_HREF_ALLOW``: ``scheme://host[:port]``) are read, and the host's
addresses are checked like a webhook target's (:mod:`service.webhooks`): a host name must
resolve to public addresses only, a non-public address (loopback, private, link-local, ...) is
read only when an entry names that very address. The request then connects to the address that
was checked, so that DNS cannot answer differently between the check and the connection.
Redirects are not followed, proxies of the environment are not used, and the body is limited
in size and in time.
"""

from __future__ import annotations

import asyncio
import hashlib
import ipaddress
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

import httpx
from fastapi.concurrency import run_in_threadpool

from pwlreg.service import __version__
from pwlreg.service.webhooks import (
    IPAddress,
    TargetError,
    address_kind,
    pin,
    resolve_host,
    split_url,
)

_DEFAULT_PORTS = {"http": 80, "https": 443}
_CHUNK = 64 * 1024


class FetchError(Exception):
    """An allowed URL that could not be read; the message says why."""


class TooLarge(Exception):
    """The body of a URL is larger than the limit."""


@dataclass(frozen=True)
class Origin:
    """One allowed origin: scheme, host (lower case, an IP address as written by
    :mod:`ipaddress`) and port."""

    scheme: str
    host: str
    port: int


def _origin(scheme: str, host: str, port: int | None) -> Origin:
    scheme = scheme.lower()
    host = host.lower().rstrip(".")
    try:
        host = str(ipaddress.ip_address(host.strip("[]")))
    except ValueError:
        pass
    return Origin(scheme, host, port or _DEFAULT_PORTS[scheme])


@dataclass(frozen=True)
class HrefAllowList:
    """The origins inputs may be read from (``PWLREG_HREF_ALLOW``)."""

    origins: frozenset[Origin] = frozenset()

    @classmethod
    def parse(cls, text: str | None) -> HrefAllowList:
        """Parse comma-separated ``scheme://host[:port]`` entries; ValueError naming a
        malformed one."""
        origins = set()
        for raw in (text or "").split(","):
            entry = raw.strip()
            if not entry:
                continue
            try:
                parts = urlsplit(entry)
                port = parts.port
            except ValueError:
                parts, port = None, None
            if (
                parts is None
                or parts.scheme.lower() not in _DEFAULT_PORTS
                or not parts.hostname
                or parts.path not in ("", "/")
                or parts.query
                or parts.fragment
                or parts.username is not None
            ):
                raise ValueError(
                    f"PWLREG_HREF_ALLOW: {entry!r} is not an origin 'http(s)://host[:port]'"
                )
            origins.add(_origin(parts.scheme, parts.hostname, port))
        return cls(frozenset(origins))

    def __bool__(self) -> bool:
        return bool(self.origins)

    def allows_address(self, origin: Origin, address: IPAddress) -> bool:
        """True if an entry of the same scheme and port names ``address`` itself."""
        return Origin(origin.scheme, str(address), origin.port) in self.origins


async def check_href(url: str, allow: HrefAllowList) -> tuple[Origin, IPAddress]:
    """Check that ``url`` may be read: an allowed origin, no credentials, and addresses that
    pass (:class:`HrefAllowList`). The host is resolved once, in a thread.

    Returns
    -------
    origin : Origin
    address : IPv4Address or IPv6Address
        The checked address to connect to.

    Raises
    ------
    TargetError
        Saying why the URL is refused.
    """
    if not allow:
        raise TargetError("this service reads no input by reference (PWLREG_HREF_ALLOW is empty)")
    parts = split_url(url)
    port = parts.port
    scheme = parts.scheme.lower()
    if scheme not in _DEFAULT_PORTS or not parts.hostname:
        raise TargetError("the URL must be an absolute http or https URL")
    if parts.username is not None:
        raise TargetError("credentials in the URL are not accepted")
    origin = _origin(scheme, parts.hostname, port)
    if origin not in allow.origins:
        raise TargetError(
            f"{origin.scheme}://{parts.netloc} is not among the origins this service reads "
            "inputs from"
        )
    addresses = await run_in_threadpool(resolve_host, parts.hostname, origin.port)
    for address in addresses:
        kind = address_kind(address)
        if kind is not None and not allow.allows_address(origin, address):
            raise TargetError(
                f"the host {parts.hostname!r} resolves to the {kind} address {address}, which "
                "this service does not read from"
            )
    return origin, addresses[0]


async def fetch_href(
    url: str, allow: HrefAllowList, dest: Path, *, max_bytes: int, timeout: float
) -> tuple[int, str]:
    """Read the allowed ``url`` (:func:`check_href`) into the file ``dest``.

    Parameters
    ----------
    url : str
    allow : HrefAllowList
    dest : pathlib.Path
        Written (created or truncated).
    max_bytes : int
        Largest accepted body (after content decoding), in bytes.
    timeout : float
        Limit of the whole exchange (connection, answer, body), in seconds.

    Returns
    -------
    size : int
        Bytes written.
    digest : str
        Their SHA-256, hex.

    Raises
    ------
    TargetError
        The URL is refused (not read).
    TooLarge
        The declared or received body is over ``max_bytes``.
    FetchError
        A connection error, a timeout, a redirect or an answer other than 200.
    """
    _, address = await check_href(url, allow)
    request = pin(url, address)
    digest = hashlib.sha256()
    size = 0
    try:
        async with asyncio.timeout(timeout), httpx.AsyncClient(
            timeout=timeout, follow_redirects=False, trust_env=False
        ) as client, client.stream(
            "GET", request.url,
            headers={**request.headers, "User-Agent": f"pwlreg/{__version__}"},
            extensions=request.extensions,
        ) as response:
            if response.status_code != 200:
                where = response.headers.get("location")
                raise FetchError(
                    f"the URL answered HTTP {response.status_code}"
                    + (f" (a redirect to {where}, which is not followed)" if where else "")
                )
            declared = response.headers.get("content-length", "")
            if declared.isdigit() and int(declared) > max_bytes:
                raise TooLarge(f"the URL announces {declared} bytes")
            with dest.open("wb") as out:
                async for chunk in response.aiter_bytes(_CHUNK):
                    size += len(chunk)
                    if size > max_bytes:
                        raise TooLarge(f"the URL sent more than {max_bytes} bytes")
                    out.write(chunk)
                    digest.update(chunk)
    except TimeoutError:
        raise FetchError(f"reading the URL took longer than {timeout:g} s") from None
    except httpx.HTTPError as exc:
        raise FetchError(f"the URL could not be read ({type(exc).__name__}: {exc})") from None
    return size, digest.hexdigest()
