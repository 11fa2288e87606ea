"""Webhooks: a job's status document POSTed, signed, to the client's URL when the job ends;
retries with backoff, a durable outbox, and the refusal of targets in the service's own
networks."""

from __future__ import annotations

import hashlib
import hmac
import json
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import timedelta
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import pytest

from pwlreg.service.problems import Problem
from pwlreg.service.settings import Settings
from pwlreg.service.store import JobStatus, JobStore, utcnow
from pwlreg.service.webhooks import (
    SECRET_FILE,
    AllowList,
    TargetError,
    Webhooks,
    check_target,
    load_secret,
    parse_callback,
    sign,
)
from tests.service.helpers import Pair, Server, assert_problem, submit, wait_for

SECRET = "test-webhook-secret"


# --- a tiny receiver ---------------------------------------------------------------------------


@dataclass
class Delivery:
    path: str
    headers: dict[str, str]
    body: bytes


@dataclass
class Receiver:
    """An HTTP server on 127.0.0.1 recording every POST. Paths decide the answer: ``/ok/...``
    200, ``/flaky/...`` 500 twice then 200, ``/down/...`` always 500."""

    url: str = ""
    deliveries: list[Delivery] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def to(self, path: str) -> list[Delivery]:
        with self.lock:
            return [d for d in self.deliveries if d.path == path]


@pytest.fixture(scope="module")
def receiver() -> Iterator[Receiver]:
    state = Receiver()

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802 (http.server's name)
            body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
            with state.lock:
                state.deliveries.append(Delivery(self.path, dict(self.headers), body))
                seen = sum(d.path == self.path for d in state.deliveries)
            kind = self.path.split("/")[1]
            ok = kind == "ok" or (kind == "flaky" and seen > 2)
            self.send_response(200 if ok else 500)
            self.send_header("Content-Length", "0")
            self.end_headers()

        def log_message(self, *args: Any) -> None:
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    state.url = f"http://127.0.0.1:{httpd.server_address[1]}"
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield state
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture(scope="module")
def hook_server(start_server: Callable[..., Server]) -> Server:
    """A server that may call 127.0.0.1, with fast retries (0.05 s, doubling, 3 attempts)."""
    return start_server(
        PWLREG_WEBHOOK_ALLOW="127.0.0.1",
        PWLREG_WEBHOOK_SECRET=SECRET,
        PWLREG_WEBHOOK_RETRY_DELAY="0.05",
        PWLREG_WEBHOOK_MAX_ATTEMPTS="3",
    )


def _submit_hook(client: httpx.Client, pair: Pair, **fields: str) -> httpx.Response:
    files = {
        "reference": ("reference.png", pair.reference_png, "image/png"),
        "moving": ("moving.png", pair.moving_png, "image/png"),
        "points": ("points.json", pair.points_json, "application/json"),
    }
    return client.post("/v1/jobs", files=files, data=fields)


def _verify(delivery: Delivery, secret: str = SECRET) -> None:
    expected = "sha256=" + hmac.new(secret.encode(), delivery.body, hashlib.sha256).hexdigest()
    assert hmac.compare_digest(delivery.headers["X-Pwlreg-Signature"], expected)
    assert delivery.headers["Content-Type"] == "application/json"


def _settled(job: dict[str, Any]) -> bool:
    hook = job.get("webhook") or {}
    return job["status"] in ("successful", "failed", "dismissed") and hook.get("state") in (
        "delivered", "failed", "skipped")


# --- over real HTTP ------------------------------------------------------------------------------


def test_a_finished_job_is_posted_once_signed_with_its_status_document(
    hook_server: Server, receiver: Receiver, pair: Pair
) -> None:
    with hook_server.client() as client:
        response = _submit_hook(client, pair, callback=f"{receiver.url}/ok/one")
        assert response.status_code == 201, response.text
        created = response.json()
        assert created["webhook"]["state"] == "waiting"
        assert created["webhook"]["success_uri"] == f"{receiver.url}/ok/one"
        job = wait_for(client, created["id"], _settled)
        time.sleep(0.3)  # no second delivery comes
    assert job["status"] == "successful"
    assert job["webhook"]["state"] == "delivered" and job["webhook"]["attempts"] == 1
    assert job["webhook"]["event"] == "successful" and job["webhook"]["last_error"] is None
    [delivery] = receiver.to("/ok/one")
    _verify(delivery)
    assert delivery.headers["X-Pwlreg-Event"] == "job.successful"
    assert delivery.headers["X-Pwlreg-Delivery"] == job["webhook"]["delivery_id"]
    body = json.loads(delivery.body)
    # The document of GET /v1/jobs/{id}, links absolute, the delivery under way.
    assert body["links"] == [
        {**link, "href": hook_server.url + link["href"]} for link in job["links"]
    ]
    assert body["webhook"]["state"] == "pending" and body["webhook"]["attempts"] == 0
    for member in ("links", "webhook"):
        body.pop(member), job.pop(member)
    assert body == job


def test_failed_attempts_are_retried_with_backoff_until_delivered(
    hook_server: Server, receiver: Receiver, pair: Pair
) -> None:
    with hook_server.client() as client:
        response = _submit_hook(client, pair, callback=f"{receiver.url}/flaky/two")
        assert response.status_code == 201, response.text
        job = wait_for(client, response.json()["id"], _settled)
    assert job["webhook"]["state"] == "delivered", job["webhook"]
    assert job["webhook"]["attempts"] == 3 and job["webhook"]["last_error"] is None
    deliveries = receiver.to("/flaky/two")
    assert len(deliveries) == 3
    assert len({d.headers["X-Pwlreg-Delivery"] for d in deliveries}) == 1
    for delivery in deliveries:
        _verify(delivery)


def test_a_target_that_keeps_failing_is_given_up_and_recorded(
    hook_server: Server, receiver: Receiver, pair: Pair
) -> None:
    with hook_server.client() as client:
        response = _submit_hook(client, pair, callback=f"{receiver.url}/down/three")
        job = wait_for(client, response.json()["id"], _settled)
    assert job["webhook"]["state"] == "failed"
    assert job["webhook"]["attempts"] == 3 and job["webhook"]["last_error"] == "HTTP 500"
    assert len(receiver.to("/down/three")) == 3


def test_ogc_subscriber_announces_a_dismissed_job_to_its_failed_uri(
    hook_server: Server, receiver: Receiver, pair: Pair
) -> None:
    subscriber = {"successUri": f"{receiver.url}/ok/four-success",
                  "failedUri": f"{receiver.url}/ok/four-failed"}
    with hook_server.client() as client:
        response = _submit_hook(client, pair, subscriber=json.dumps(subscriber))
        assert response.status_code == 201, response.text
        job_id = response.json()["id"]
        assert client.delete(f"/v1/jobs/{job_id}").status_code == 204
        job = wait_for(client, job_id, lambda j: _settled(j) and j["status"] == "dismissed"
                       and j["webhook"]["event"] == "dismissed")
    assert job["webhook"]["state"] == "delivered"
    [delivery] = receiver.to("/ok/four-failed")
    _verify(delivery)
    assert delivery.headers["X-Pwlreg-Event"] == "job.dismissed"
    assert json.loads(delivery.body)["status"] == "dismissed"


@pytest.mark.parametrize(
    ("fields", "field"),
    [({"callback": "ftp://127.0.0.1/x"}, "callback"),
     ({"callback": "not a url"}, "callback"),
     ({"callback": "http:///nohost"}, "callback"),
     ({"callback": "http://127.0.0.1:1/a", "subscriber": '{"successUri": "http://127.0.0.1/"}'},
      "callback"),
     ({"subscriber": '{"successUri": "gopher://127.0.0.1/"}'}, "subscriber.successUri"),
     ({"subscriber": '{"callback": "http://127.0.0.1/"}'}, "subscriber"),
     ({"subscriber": "[1]"}, "subscriber")],
)
def test_malformed_targets_are_refused(
    hook_server: Server, pair: Pair, fields: dict[str, str], field: str
) -> None:
    with hook_server.client() as client:
        assert_problem(_submit_hook(client, pair, **fields), 422, field=field)


def test_targets_in_the_services_own_networks_are_refused_by_default(
    server: Server, pair: Pair
) -> None:
    with server.client() as client:
        for url in ("http://127.0.0.1:9/hook", "http://localhost/hook", "http://[::1]/",
                    "http://10.0.0.8/", "http://192.168.1.1/", "http://169.254.169.254/",
                    "http://0.0.0.0/", "http://224.0.0.1/", "http://[fd00::1]/"):
            doc = assert_problem(_submit_hook(client, pair, callback=url), 422, field="callback")
            assert "PWLREG_WEBHOOK_ALLOW" in doc["detail"], doc
        assert_problem(
            _submit_hook(client, pair, subscriber='{"failedUri": "http://127.0.0.1/"}'),
            422, field="subscriber.failedUri",
        )
        # Without a webhook, the same server accepts the job (and shows no webhook).
        response = submit(client, pair)
        assert response.status_code == 201 and response.json()["webhook"] is None


# --- without a server ----------------------------------------------------------------------------


def test_allow_list_admits_hosts_addresses_and_networks() -> None:
    allow = AllowList.parse(" 127.0.0.1, receiver.internal ,10.0.0.0/8, ::1")
    for url in ("http://127.0.0.1:8080/x", "https://10.1.2.3/", "http://[::1]:81/",
                "http://receiver.internal/hook", "http://[::ffff:127.0.0.1]/"):
        assert check_target(url, allow) == url
    for url in ("http://127.0.0.2/", "http://192.168.0.1/", "http://[fe80::1]/"):
        with pytest.raises(TargetError):
            check_target(url, allow)
    assert check_target("https://93.184.216.34/hook", AllowList.parse(None))
    with pytest.raises(ValueError, match="PWLREG_WEBHOOK_ALLOW"):
        AllowList.parse("10.0.0.0/33")
    with pytest.raises(Problem) as caught:
        parse_callback("http://x/" + "a" * 3000, None, allow)
    assert caught.value.field == "callback"
    assert parse_callback(None, None, allow) is None


def test_secret_is_generated_once_and_kept(tmp_path: Path) -> None:
    settings = Settings(_env_file=None, data_dir=tmp_path)  # type: ignore[call-arg]
    first = load_secret(settings)
    assert len(first) == 64 and (tmp_path / SECRET_FILE).stat().st_mode & 0o077 == 0
    assert load_secret(settings) == first
    given = Settings(_env_file=None, data_dir=tmp_path, webhook_secret="s")  # type: ignore[call-arg]
    assert load_secret(given) == b"s"
    assert sign(b"k", b"{}") == "sha256=" + hmac.new(b"k", b"{}", hashlib.sha256).hexdigest()


def test_a_pending_delivery_survives_a_restart(tmp_path: Path, receiver: Receiver) -> None:
    settings = Settings(  # type: ignore[call-arg]
        _env_file=None, data_dir=tmp_path, webhook_allow="127.0.0.1", webhook_retry_delay=0.05
    )
    url = f"{receiver.url}/ok/restart"
    store = JobStore.from_url(settings.resolved_database_url)
    store.create_schema()
    store.create("j1", {}, False, 3, callback={"success_uri": url, "failed_uri": url,
                                                  "base_url": "http://svc"})
    store.dismiss("j1")
    assert store.arm_webhooks(lambda job: url) == ["j1"]
    job = store.get("j1")
    assert job is not None and job.webhook_state == "pending"
    # The process dies after claiming the delivery (the hold keeps it for a while) ...
    assert store.claim_webhook(job, hold_seconds=0.2)
    store.dispose()
    # ... the next process delivers it once the hold is over.
    store = JobStore.from_url(settings.resolved_database_url)
    store.create_schema()
    webhooks = Webhooks(settings, store, lambda job: b'{"id": "%s"}' % job.id.encode(), b"k",
                        poll_interval=0.05)
    webhooks.start()
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not receiver.to("/ok/restart"):
            time.sleep(0.05)
        time.sleep(0.2)
    finally:
        webhooks.stop()
    [delivery] = receiver.to("/ok/restart")
    assert delivery.body == b'{"id": "j1"}'
    assert delivery.headers["X-Pwlreg-Event"] == "job.dismissed"
    _verify(delivery, "k")
    job = store.get("j1")
    assert job is not None and job.status == JobStatus.dismissed
    assert job.webhook_state == "delivered" and job.webhook_attempts == 1
    assert job.webhook_next is None and job.webhook_last is not None
    assert job.webhook_last <= utcnow() + timedelta(seconds=1)
    store.dispose()


def test_deliveries_go_to_the_address_that_was_checked() -> None:
    from pwlreg.service.webhooks import pinned_target

    pinned = pinned_target("http://localhost:8123/hook?x=1", AllowList.parse("127.0.0.1"))
    assert pinned.url == "http://127.0.0.1:8123/hook?x=1"
    assert pinned.headers == {"Host": "localhost:8123"} and pinned.extensions == {}
    by_name = pinned_target("http://localhost:8123/hook", AllowList.parse("localhost"))
    assert by_name.url == "http://localhost:8123/hook" and by_name.headers == {}
    tls = pinned_target("https://93.184.216.34/hook", AllowList.parse(None))
    assert tls.url == "https://93.184.216.34:443/hook"
    assert tls.extensions == {"sni_hostname": "93.184.216.34"}
