"""Webhooks: the service POSTs a job's status document to the client's URL when the job ends.

A client gives a ``callback`` URL (every end) or an OGC ``subscriber`` object (``successUri``
for a successful job, ``failedUri`` for a failed or dismissed one) with the job. The target is
checked at submission and again before every attempt: http or https only, and no address of
the service's own networks (loopback, link-local, private, multicast, reserved, unspecified)
unless ``PWLREG_WEBHOOK_ALLOW`` allows it.

Delivery never blocks a worker. The job row is the outbox: a thread of the API process finds
finished jobs whose end has no delivery yet, opens one (``webhook_*`` columns: state, attempts,
next time, last error, delivery id) and sends it, retrying with exponential backoff. Since the
state lives in the database, a delivery survives a restart of the server.

Each request carries ``X-Pwlreg-Signature: sha256=<hex>``, the HMAC-SHA256 of the exact body
under the service's webhook secret (``PWLREG_WEBHOOK_SECRET``, or a random key kept in
``<data_dir>/webhook_secret``), ``X-Pwlreg-Event`` (``job.<status>``) and ``X-Pwlreg-Delivery``
(the same for every attempt of one delivery, so that a receiver can drop duplicates).
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import logging
import os
import secrets
import socket
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any
from urllib.parse import SplitResult, urlsplit, urlunsplit

import httpx

from pwlreg.core.errors import InputError
from pwlreg.core.io import load_json
from pwlreg.service import __version__
from pwlreg.service.logs import job_extra
from pwlreg.service.settings import Settings
from pwlreg.service.store import Job, JobStatus, JobStore, utcnow

log = logging.getLogger(__name__)

SECRET_FILE = "webhook_secret"
MAX_URL_LENGTH = 2048
SIGNATURE_HEADER = "X-Pwlreg-Signature"
EVENT_HEADER = "X-Pwlreg-Event"
DELIVERY_HEADER = "X-Pwlreg-Delivery"

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


class TargetError(ValueError):
    """A URL the service refuses to call (a webhook target, an input given by reference); the
    message says why (no secret in it)."""


# --- allow-list and target checks ------------------------------------------------------------


@dataclass(frozen=True)
class AllowList:
    """Targets allowed despite a non-public address: host names and IP networks."""

    hosts: frozenset[str] = frozenset()
    networks: tuple[IPNetwork, ...] = ()

    @classmethod
    def parse(cls, text: str | None) -> AllowList:
        """Parse ``PWLREG_WEBHOOK_ALLOW`` (comma-separated host names, IPs or CIDR networks)."""
        hosts: set[str] = set()
        networks: list[IPNetwork] = []
        for raw in (text or "").split(","):
            entry = raw.strip().lower()
            if not entry:
                continue
            try:
                networks.append(ipaddress.ip_network(entry.strip("[]"), strict=False))
            except ValueError:
                if "/" in entry or not all(c.isalnum() or c in "-._" for c in entry):
                    raise ValueError(
                        f"PWLREG_WEBHOOK_ALLOW: {entry!r} is neither a host name, an IP address "
                        "nor a CIDR network"
                    ) from None
                hosts.add(entry.rstrip("."))
        return cls(frozenset(hosts), tuple(networks))

    def allows_host(self, host: str) -> bool:
        return host.lower().rstrip(".") in self.hosts

    def allows_address(self, address: IPAddress) -> bool:
        return any(address in network for network in self.networks)


def address_kind(address: IPAddress) -> str | None:
    """Why ``address`` is not a public target (None: it is public): ``loopback``,
    ``link-local``, ``multicast``, ``unspecified``, ``private``, ``reserved`` or ``non-public``."""
    for kind in ("loopback", "link_local", "multicast", "unspecified", "private", "reserved"):
        if getattr(address, f"is_{kind}"):
            return kind.replace("_", "-")
    if not address.is_global:
        return "non-public"
    return None


def resolve_host(host: str, port: int) -> list[IPAddress]:
    """Every address of ``host`` (an IP literal is its own address), IPv4-mapped IPv6
    addresses as IPv4; :class:`TargetError` if the name cannot be resolved."""
    try:
        literal = ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        pass
    else:
        return [_unmapped(literal)]
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as exc:
        raise TargetError(f"the host {host!r} cannot be resolved ({exc})") from None
    return [_unmapped(ipaddress.ip_address(str(info[4][0]).split("%")[0])) for info in infos]


def _unmapped(address: IPAddress) -> IPAddress:
    """An IPv4-mapped IPv6 address as the IPv4 address it is."""
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped
    return address


def split_url(url: str) -> SplitResult:
    """The parts of a URL a client gave (webhook or input), or :class:`TargetError` if it is
    too long, holds white space or control characters, or does not parse (port included)."""
    if len(url) > MAX_URL_LENGTH:
        raise TargetError(f"the URL is longer than {MAX_URL_LENGTH} characters")
    if any(c.isspace() or ord(c) < 0x20 for c in url):
        raise TargetError("the URL contains white space or control characters")
    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 (parsing the port is what raises for a bad one)
    except ValueError as exc:
        raise TargetError(f"not a valid URL ({exc})") from None
    return parts


def check_target(url: str, allow: AllowList) -> str:
    """Check a webhook URL: http(s), a host, and (unless allowed) only public addresses.

    Returns
    -------
    str
        The URL, unchanged.

    Raises
    ------
    TargetError
        Saying what is wrong.
    """
    parts = split_url(url)
    port = parts.port
    if parts.scheme.lower() not in ("http", "https"):
        raise TargetError(f"the URL must be http or https, not {parts.scheme or 'relative'!r}")
    host = parts.hostname
    if not host:
        raise TargetError("the URL has no host")
    if allow.allows_host(host):
        return url
    port = port or (443 if parts.scheme.lower() == "https" else 80)
    for address in resolve_host(host, port):
        kind = address_kind(address)
        if kind is not None and not allow.allows_address(address):
            raise TargetError(
                f"the host {host!r} resolves to the {kind} address {address}; webhooks to the "
                "service's own networks are refused unless PWLREG_WEBHOOK_ALLOW allows them"
            )
    return url


@dataclass(frozen=True)
class PinnedRequest:
    """A webhook request bound to the address that was checked (so that DNS cannot answer
    differently between the check and the connection)."""

    url: str
    headers: dict[str, str]
    extensions: dict[str, Any]


def pinned_target(url: str, allow: AllowList) -> PinnedRequest:
    """Check ``url`` (:func:`check_target`) and bind it to the first address that passed.

    A host allowed by name keeps its URL (the operator vouches for it). Otherwise the request
    goes to the checked IP address, with the original ``Host`` header and, for https, the
    original name for SNI and certificate verification.

    Raises
    ------
    TargetError
        As :func:`check_target`.
    """
    check_target(url, allow)
    parts = urlsplit(url)
    host = parts.hostname or ""
    if allow.allows_host(host):
        return PinnedRequest(url, {}, {})
    https = parts.scheme.lower() == "https"
    return pin(url, resolve_host(host, parts.port or (443 if https else 80))[0])


def pin(url: str, address: IPAddress) -> PinnedRequest:
    """A request for the http(s) ``url`` that connects to ``address`` (already checked), with
    the URL's ``Host`` header and, for https, its host name for SNI and certificate
    verification."""
    parts = urlsplit(url)
    https = parts.scheme.lower() == "https"
    port = parts.port or (443 if https else 80)
    literal = f"[{address}]" if isinstance(address, ipaddress.IPv6Address) else str(address)
    pinned = urlunsplit((parts.scheme, f"{literal}:{port}", parts.path or "/", parts.query, ""))
    headers = {"Host": parts.netloc.rsplit("@", 1)[-1]}
    extensions = {"sni_hostname": parts.hostname or ""} if https else {}
    return PinnedRequest(pinned, headers, extensions)


def parse_callback(
    callback: str | None, subscriber: str | None, allow: AllowList
) -> dict[str, str | None] | None:
    """The job's webhook from the form fields ``callback`` (a URL) or ``subscriber`` (OGC:
    a JSON object with ``successUri`` and/or ``failedUri``; ``inProgressUri`` is ignored).

    Returns
    -------
    dict or None
        ``{"success_uri": ..., "failed_uri": ...}`` (a failed and a dismissed job go to
        ``failed_uri``), None without either field.

    Raises
    ------
    service.problems.Problem
        422 with ``field`` ``callback`` or ``subscriber[.<member>]``.
    """
    from pwlreg.service.problems import from_input_error, invalid_input

    if callback is not None and subscriber is not None:
        raise invalid_input("give either callback or subscriber, not both", "callback")
    if callback is not None:
        url = callback.strip()
        try:
            check_target(url, allow)
        except TargetError as exc:
            raise invalid_input(f"callback: {exc}", "callback") from None
        return {"success_uri": url, "failed_uri": url}
    if subscriber is None:
        return None
    try:
        value = load_json(subscriber, "subscriber")
    except InputError as exc:
        raise from_input_error(exc) from None
    members = ("successUri", "failedUri", "inProgressUri")
    if (
        not isinstance(value, dict)
        or set(value) - set(members)
        or not any(value.get(m) for m in members[:2])
    ):
        raise invalid_input(
            'subscriber must be a JSON object with successUri and/or failedUri, e.g. '
            '{"successUri": "https://example.org/done", "failedUri": "https://example.org/failed"}',
            "subscriber",
        )
    urls: dict[str, str | None] = {}
    for member, key in (("successUri", "success_uri"), ("failedUri", "failed_uri")):
        url = value.get(member)
        if url is None:
            urls[key] = None
            continue
        if not isinstance(url, str):
            raise invalid_input(f"subscriber.{member} must be a string", f"subscriber.{member}")
        try:
            urls[key] = check_target(url.strip(), allow)
        except TargetError as exc:
            raise invalid_input(f"subscriber.{member}: {exc}", f"subscriber.{member}") from None
    return urls


def target_of(job: Job) -> str | None:
    """The URL the current end of ``job`` is announced to (None: none)."""
    if not job.callback:
        return None
    key = "success_uri" if job.status == JobStatus.successful else "failed_uri"
    return job.callback.get(key)


# --- secret and signature --------------------------------------------------------------------


def load_secret(settings: Settings) -> bytes:
    """The webhook key: ``PWLREG_WEBHOOK_SECRET``, else the one kept in the data directory
    (generated, readable by the owner only, at the first start)."""
    if settings.webhook_secret is not None and settings.webhook_secret.get_secret_value():
        return settings.webhook_secret.get_secret_value().encode()
    path = Path(settings.data_dir) / SECRET_FILE
    try:
        return path.read_text().strip().encode()
    except FileNotFoundError:
        pass
    path.parent.mkdir(parents=True, exist_ok=True)
    secret = secrets.token_hex(32)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:  # another process made it meanwhile
        return path.read_text().strip().encode()
    with os.fdopen(fd, "w") as f:
        f.write(secret + "\n")
        f.flush()
        os.fsync(f.fileno())
    log.info("webhook secret generated in %s", path)
    return secret.encode()


def sign(secret: bytes, body: bytes) -> str:
    """The ``X-Pwlreg-Signature`` value of ``body``."""
    return "sha256=" + hmac.new(secret, body, hashlib.sha256).hexdigest()


# --- delivery ----------------------------------------------------------------------------------


class Webhooks:
    """The delivery loop: a thread of the API process reading the outbox columns of the job
    store, with a few threads sending the requests.

    Parameters
    ----------
    settings : Settings
    store : JobStore
    render : callable
        The status document of a job as JSON bytes (links absolute).
    secret : bytes
        Key of the signatures.
    poll_interval : float
        Longest sleep between two looks at the store (ends of jobs are also announced with
        :meth:`wake`).
    """

    def __init__(
        self,
        settings: Settings,
        store: JobStore,
        render: Callable[[Job], bytes],
        secret: bytes,
        poll_interval: float = 1.0,
    ) -> None:
        self.settings = settings
        self.store = store
        self.render = render
        self.secret = secret
        self.allow = AllowList.parse(settings.webhook_allow)
        self.poll_interval = poll_interval
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._client: httpx.Client | None = None
        self._inflight: set[str] = set()
        self._lock = threading.Lock()

    def start(self) -> None:
        timeout = self.settings.webhook_timeout
        self._client = httpx.Client(
            timeout=httpx.Timeout(timeout, connect=min(timeout, 5.0)),
            follow_redirects=False,
            trust_env=False,  # no proxy from the environment
            headers={"User-Agent": f"pwlreg/{__version__} webhook"},
        )
        self._pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix="webhook")
        self._thread = threading.Thread(target=self._run, name="webhooks", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Look at the store now (a job just ended)."""
        self._wake.set()

    def stop(self) -> None:
        """Stop the loop; an attempt under way ends within the timeout. Pending deliveries
        stay in the store for the next start."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        if self._client is not None:
            self._client.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            wait = self.poll_interval
            try:
                self.store.arm_webhooks(target_of)
                now = utcnow()
                for job in self.store.due_webhooks(now):
                    with self._lock:
                        if job.id in self._inflight:
                            continue
                    if self.store.claim_webhook(job, self._hold_seconds()):
                        with self._lock:
                            self._inflight.add(job.id)
                        assert self._pool is not None
                        self._pool.submit(self._attempt, job)
                upcoming = self.store.next_webhook_time()
                if upcoming is not None:
                    wait = max(0.01, min(wait, (upcoming - utcnow()).total_seconds()))
            except Exception:  # noqa: BLE001 (keep delivering after a database hiccup)
                log.exception("webhook pass failed")
            self._wake.wait(wait)
            self._wake.clear()

    def _hold_seconds(self) -> float:
        return 2 * self.settings.webhook_timeout + 5.0

    def _attempt(self, job: Job) -> None:
        try:
            self.deliver(job)
        except Exception:  # noqa: BLE001
            log.exception("webhook of job %s: attempt failed unexpectedly", job.id,
                          extra=job_extra(job.id, job.owner))
        finally:
            with self._lock:
                self._inflight.discard(job.id)
            self._wake.set()

    def deliver(self, job: Job) -> bool:
        """Make one attempt of the pending delivery of ``job`` and record its outcome."""
        current = self.store.get(job.id)
        if current is None or current.webhook_delivery != job.webhook_delivery:
            return False  # deleted, or it ended again: a newer delivery replaces this one
        url = target_of(current)
        attempts = (current.webhook_attempts or 0) + 1
        error: str | None = None
        if url is None:
            error = "no target"
        else:
            try:
                # DNS may have changed since the submission; the request goes to the address
                # checked now.
                target = pinned_target(url, self.allow)
            except TargetError as exc:
                error = f"target refused: {exc}"
        if error is None:
            assert url is not None and self._client is not None
            body = self.render(current)
            headers = {
                **target.headers,
                "Content-Type": "application/json",
                SIGNATURE_HEADER: sign(self.secret, body),
                EVENT_HEADER: f"job.{current.status.value}",
                DELIVERY_HEADER: current.webhook_delivery or "",
            }
            try:
                # Streamed and closed unread: only the status code counts, so a large answer
                # costs nothing.
                with self._client.stream("POST", target.url, content=body, headers=headers,
                                         extensions=target.extensions) as response:
                    code = response.status_code
                if 200 <= code < 300:
                    self.store.record_webhook(
                        job.id, current.webhook_delivery or "", attempts, "delivered", None, None
                    )
                    log.info("webhook of job %s delivered (attempt %d)", job.id, attempts,
                             extra=job_extra(job.id, job.owner))
                    return True
                error = f"HTTP {code}"
                if 300 <= code < 400:
                    error += " (redirects are not followed)"
            except httpx.HTTPError as exc:
                error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        settings = self.settings
        if attempts >= settings.webhook_max_attempts:
            state, next_time = "failed", None
            log.warning("webhook of job %s failed after %d attempts: %s", job.id, attempts, error,
                        extra=job_extra(job.id, job.owner))
        else:
            delay = settings.webhook_retry_delay * 2 ** (attempts - 1)
            state, next_time = "pending", utcnow() + timedelta(seconds=delay)
        self.store.record_webhook(
            job.id, current.webhook_delivery or "", attempts, state, error[:500], next_time
        )
        return False


def webhook_info(job: Job) -> dict[str, Any] | None:
    """The ``webhook`` member of the status document (None for a job without a callback)."""
    if not job.callback:
        return None
    return {
        "success_uri": job.callback.get("success_uri"),
        "failed_uri": job.callback.get("failed_uri"),
        "event": job.webhook_event,
        "state": job.webhook_state or "waiting",
        "attempts": job.webhook_attempts or 0,
        "last_attempt": job.webhook_last,
        "last_error": job.webhook_error,
        "delivery_id": job.webhook_delivery,
    }
