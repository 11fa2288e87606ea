"""Scale-out mode end to end, all real: the API (``pwlreg serve`` with ``PWLREG_QUEUE=celery``),
``pwlreg worker`` processes, PostgreSQL and Redis.

Every registration spends a moment in 'matching' (progress every 50 ms) before the real one, so
that a job can be caught running, and writes a line to a ledger when it runs to completion
(:mod:`tests.service.scaleout_runner`): a registration that ran twice would show twice.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import httpx
import numpy as np
import psycopg
import pytest

from pwlreg.core.io import read_image
from tests.service.helpers import (
    Pair,
    Server,
    make_pair,
    metric_samples,
    one,
    submit,
    wait_for,
)
from tests.service.scaleout import Worker, broker, database  # noqa: F401 (fixtures)
from tests.service.scaleout_runner import digest

pytestmark = pytest.mark.slow

JOBS = 20
ENV = {
    "PWLREG_RUNNER": "tests.service.scaleout_runner:ledger_register",
    "PWLREG_TEST_SLOW_SECONDS": "0.4",
    "PWLREG_LEASE_SECONDS": "2",
    "PWLREG_PROGRESS_INTERVAL": "0.1",
    "PWLREG_MAX_ATTEMPTS": "3",
}


@dataclass
class Cluster:
    """The API, the workers and what they share."""

    api: Server
    workers: list[Worker]
    env: dict[str, str]
    data_dir: Path
    database: str
    ledger: Path
    restarts: list[Server] = field(default_factory=list)

    def rows(self, query: str) -> list[tuple]:
        with psycopg.connect(self.database.replace("+psycopg", "")) as db:
            return db.execute(query).fetchall()

    def freeze_holder(
        self, digests: Mapping[str, str], timeout: float = 30.0
    ) -> tuple[str, str, Worker]:
        """SIGSTOP a worker while it holds one of the jobs of ``digests`` (job id -> digest of
        its reference image) in its slow 'matching', before its registration completes;
        returns the job, the lease owner of the attempt and the frozen worker."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for job_id, owner in self.rows(
                "SELECT id, lease_owner FROM jobs WHERE status = 'running' AND progress > 0 "
                "AND progress < 10"
            ):
                pid = int(owner.split(":")[1])  # host:pid:attempt, the pool process
                for worker in self.workers:
                    if job_id not in digests or pid not in worker.pids():
                        continue
                    # Frozen, it cannot go on between these looks and what the caller does.
                    # The row's progress is the heartbeat's, a beat and a commit behind the
                    # registration: under disk load the registration was seen to complete
                    # (its ledger line written) while the row still said 8.8 %, so the
                    # ledger decides whether it has.
                    worker.signal(signal.SIGSTOP)
                    if self.rows(f"SELECT 1 FROM jobs WHERE id = '{job_id}' AND status = "
                                 f"'running' AND lease_owner = '{owner}' AND progress < 10"
                                 ) and digests[job_id] not in self.completions():
                        return job_id, owner, worker
                    worker.signal(signal.SIGCONT)
            time.sleep(0.05)
        raise AssertionError("no job was seen running")

    def kill_holder(self, digests: Mapping[str, str], timeout: float = 30.0
                    ) -> tuple[str, Worker]:
        """SIGKILL a worker while it holds a job in its slow 'matching' (before its
        registration completes, see :meth:`freeze_holder`); returns the job and the worker."""
        job_id, _, worker = self.freeze_holder(digests, timeout)
        worker.kill()
        return job_id, worker

    def completions(self) -> list[str]:
        """Digests of the reference images of the registrations that ran to completion."""
        text = self.ledger.read_text() if self.ledger.exists() else ""
        return [line.split()[0] for line in text.splitlines()]


@pytest.fixture()
def cluster(
    start_server: Callable[..., Server], database: str, broker: dict[str, str],  # noqa: F811
    tmp_path: Path,
) -> Iterator[Callable[..., Cluster]]:
    """Start the API, then ``workers`` workers: ``cluster(workers=2, **env)``."""
    made: list[Cluster] = []

    def make(workers: int = 2, **env: str) -> Cluster:
        ledger = tmp_path / "ledger"
        env = {**ENV, **broker, "PWLREG_DATABASE_URL": database,
               "PWLREG_TEST_LEDGER": str(ledger), **env}
        data_dir = tmp_path / "data"
        # Side by side, as compose starts them: the workers wait for the API's migration.
        started = [Worker(data_dir, env, f"worker{i}").start() for i in range(workers)]
        api = start_server(data_dir=data_dir, log_level="info", **env)
        group = Cluster(api, started, env, data_dir, database, ledger)
        made.append(group)
        for worker in started:
            worker.wait_ready()
        return group

    yield make
    for group in made:
        for worker in group.workers:  # all at once: each waits for its warm shutdown
            worker.terminate()
        for worker in group.workers:
            worker.stop()
        for server in (group.api, *group.restarts):
            server.stop()


@pytest.fixture()
def hooks() -> Iterator[tuple[str, list[tuple[dict[str, str], bytes]]]]:
    """A webhook receiver on 127.0.0.1: its URL and the (headers, body) of every POST."""
    received: list[tuple[dict[str, str], bytes]] = []

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802 (http.server's name)
            body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
            received.append((dict(self.headers), body))
            self.send_response(200)
            self.send_header("Content-Length", "0")
            self.end_headers()

        def log_message(self, *args: object) -> None:
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/hook", received
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture(scope="module")
def pairs() -> list[Pair]:
    """One pair per job, each with its own texture."""
    return [make_pair(seed=100 + i) for i in range(JOBS)]


def _digests(ids: list[str], pairs: list[Pair]) -> dict[str, str]:
    """Job id -> what the ledger records of its registration."""
    return {job_id: digest(read_image(pair.reference_png))
            for job_id, pair in zip(ids, pairs, strict=True)}


def _check_results(client: httpx.Client, ids: list[str], pairs: list[Pair]) -> None:
    """Every job successful, and its registered image is its own reference (not another's)."""
    for i, (job_id, pair) in enumerate(zip(ids, pairs, strict=True)):
        _check_result(client, job_id, pair, pairs[(i + 1) % len(pairs)])


def _check_result(client: httpx.Client, job_id: str, pair: Pair, other: Pair) -> None:
    """The job successful, its registered image ``pair``'s reference, not ``other``'s."""
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert job["status"] == "successful", job
    png = client.get(f"/v1/jobs/{job_id}/registered.png")
    assert png.status_code == 200
    registered = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_UNCHANGED)
    inside = registered[24:-24, 24:-24, 1] > 0
    assert inside.mean() > 0.95
    grey = registered[24:-24, 24:-24, 0].astype(float)
    own = read_image(pair.reference_png)[24:-24, 24:-24]
    assert np.abs(grey - own)[inside].mean() < 2.0
    assert np.abs(grey - read_image(other.reference_png)[24:-24, 24:-24])[inside].mean() > 10.0
    mesh = client.get(f"/v1/jobs/{job_id}/mesh").json()
    assert len(mesh["reference_vertices"]) >= len(pair.reference_points)


def _check_once(group: Cluster, pairs: list[Pair], victim: str, ids: list[str]) -> None:
    """Each registration ran to completion once; only the victim needed a second attempt."""
    completions = group.completions()
    assert sorted(completions) == sorted(digest(read_image(p.reference_png)) for p in pairs)
    attempts = dict(group.rows("SELECT id, attempts FROM jobs"))
    assert attempts[victim] == 2
    assert all(attempts[job_id] == 1 for job_id in ids if job_id != victim), attempts


def test_a_worker_killed_while_it_holds_a_job(
    cluster: Callable[..., Cluster], pairs: list[Pair],
    hooks: tuple[str, list[tuple[dict[str, str], bytes]]],
) -> None:
    group = cluster(PWLREG_WEBHOOK_ALLOW="127.0.0.1")
    hook_url, received = hooks
    with group.api.client() as client:
        first = client.post("/v1/jobs", data={"callback": hook_url}, files={
            "reference": ("reference.png", pairs[0].reference_png, "image/png"),
            "moving": ("moving.png", pairs[0].moving_png, "image/png"),
            "points": ("points.json", pairs[0].points_json, "application/json"),
        })
        assert first.status_code == 201, first.text
        ids = [first.json()["id"]] + [submit(client, pair).json()["id"] for pair in pairs[1:]]
        wait_for(client, ids[4], timeout=60)  # both workers at work
        # Main and pool process at once: its message stays unacknowledged in Redis.
        victim, worker = group.kill_holder(_digests(ids, pairs))
        survivor = next(w for w in group.workers if w is not worker)
        for job_id in ids:
            wait_for(client, job_id, timeout=90)
        _check_results(client, ids, pairs)
        _check_once(group, pairs, victim, ids)
        assert f"job {victim}: successful" in survivor.log()
        # The API sees every job end (metrics, webhooks) within a second, though no worker of
        # its own ran them.
        deadline = time.monotonic() + 5
        while True:
            samples = metric_samples(client.get("/metrics").text)
            ended = one(samples, "pwlreg_job_duration_seconds_count", status="successful")
            if ended == JOBS or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert ended == JOBS
        assert one(samples, "pwlreg_workers") == 0
        while not received and time.monotonic() < deadline + 5:
            time.sleep(0.1)
        [(headers, body)] = received  # the webhook of the first job, sent by the API
        assert headers["X-Pwlreg-Event"] == "job.successful"
        assert json.loads(body)["id"] == ids[0]


def test_the_api_and_a_worker_killed_mid_run(
    cluster: Callable[..., Cluster], pairs: list[Pair], start_server: Callable[..., Server]
) -> None:
    group = cluster()
    with group.api.client() as client:
        ids = [submit(client, pair).json()["id"] for pair in pairs]
        wait_for(client, ids[2], timeout=60)
    group.api.kill()
    # With the API down the workers go on; one of them dies while it holds a job.
    victim, _ = group.kill_holder(_digests(ids, pairs))
    time.sleep(float(ENV["PWLREG_LEASE_SECONDS"]))
    api = start_server(data_dir=group.data_dir, **group.env)
    group.restarts.append(api)
    with api.client() as client:
        for job_id in ids:
            wait_for(client, job_id, timeout=90)
        _check_results(client, ids, pairs)
    _check_once(group, pairs, victim, ids)


def test_a_worker_stalled_past_its_lease_leaves_the_job_to_its_successor(
    cluster: Callable[..., Cluster], pairs: list[Pair],
    hooks: tuple[str, list[tuple[dict[str, str], bytes]]],
) -> None:
    """A worker frozen (SIGSTOP, as a starved or swapping machine) past its lease while it
    holds a job loses the job to the other worker; resumed while that one is writing the
    results, it ends its attempt without a trace: the successor's files untouched, one
    completion, one webhook."""
    group = cluster(PWLREG_WEBHOOK_ALLOW="127.0.0.1", PWLREG_LEASE_SECONDS="3")
    hook_url, received = hooks
    with group.api.client() as client:
        # The successor is caught writing by polling its work directory (tens of ms): a
        # round whose look comes too late is run again with the next job.
        for i in range(5):
            if _stall_past_lease(group, client, pairs[i], pairs[i + 1], hook_url, received):
                return
    raise AssertionError("the successor was never caught writing its results")


def _stall_past_lease(
    group: Cluster, client: httpx.Client, pair: Pair, other: Pair, hook_url: str,
    received: list[tuple[dict[str, str], bytes]],
) -> bool:
    """One round of the test above; False if the successor was not caught writing."""
    job_id = client.post("/v1/jobs", data={"callback": hook_url}, files={
        "reference": ("reference.png", pair.reference_png, "image/png"),
        "moving": ("moving.png", pair.moving_png, "image/png"),
        "points": ("points.json", pair.points_json, "application/json"),
    }).json()["id"]
    _, owner, stalled = group.freeze_holder(_digests([job_id], [pair]))
    successor = next(w for w in group.workers if w is not stalled)
    # Its heartbeat frozen too, the lease expires, the API requeues the job and the successor
    # takes it over. Frozen before its registration completed, the stalled attempt has no
    # work directory: the one that appears is the successor's, until it publishes.
    folder = group.data_dir / "jobs" / job_id
    writing: Path | None = None
    deadline = time.monotonic() + 60
    while writing is None and not (folder / "results").exists():
        assert time.monotonic() < deadline, "the job was not taken over"
        for work in folder.glob("work-*"):
            successor.signal(signal.SIGSTOP)
            if work.is_dir():
                writing = work
            else:
                successor.signal(signal.SIGCONT)
            break
        time.sleep(0.001)
    # Resumed, the stalled worker finds its lease lost and its task returns while the
    # successor is frozen mid-write.
    ended = stalled.log().count(": 'skipped'")
    stalled.signal(signal.SIGCONT)
    deadline = time.monotonic() + 30
    while stalled.log().count(": 'skipped'") == ended:
        assert time.monotonic() < deadline, stalled.log()[-3000:]
        time.sleep(0.05)
    caught = writing is not None and writing.is_dir()
    successor.signal(signal.SIGCONT)
    assert writing is None or caught, "the stalled worker removed its successor's results"
    job = wait_for(client, job_id, timeout=60)
    assert job["status"] == "successful" and job["attempts"] == 2, job
    _check_result(client, job_id, pair, other)
    assert f"job {job_id}: lease lost, attempt by {owner} abandoned" in stalled.log()
    assert f"job {job_id}: successful" not in stalled.log()
    assert successor.log().count(f"job {job_id}: successful") == 1
    # One end, one webhook (sent by the API from the job row).
    deadline = time.monotonic() + 10
    while not [b for _, b in received if json.loads(b)["id"] == job_id]:
        assert time.monotonic() < deadline, "no webhook"
        time.sleep(0.1)
    time.sleep(1.0)
    [headers] = [h for h, b in received if json.loads(b)["id"] == job_id]
    assert headers["X-Pwlreg-Event"] == "job.successful"
    return caught


def test_cancel_a_running_job(cluster: Callable[..., Cluster], pair: Pair) -> None:
    group = cluster(workers=1, PWLREG_TEST_SLOW_SECONDS="30")
    with group.api.client() as client:
        running = submit(client, pair).json()["id"]
        waiting = submit(client, pair).json()["id"]  # one worker: waits behind the first
        wait_for(client, running, lambda j: j["status"] == "running" and j["progress"] > 0)
        assert client.get(f"/v1/jobs/{waiting}").json()["status"] == "accepted"
        assert (group.data_dir / "jobs" / running / "inputs" / "reference").is_file()
        assert client.delete(f"/v1/jobs/{running}").status_code == 204
        assert client.get(f"/v1/jobs/{running}").json()["status"] == "dismissed"
        assert not (group.data_dir / "jobs" / running).exists()
        # The worker stops the registration at its next progress report (every 50 ms), far
        # before its 30 s of matching, and takes the next job.
        t0 = time.monotonic()
        wait_for(client, waiting, lambda j: j["status"] == "running", timeout=10)
        assert time.monotonic() - t0 < 10
        assert f"job {running}: stopped, dismissed by the client" in group.workers[0].log()
        assert client.delete(f"/v1/jobs/{waiting}").status_code == 204
        done = wait_for(client, running)
        assert done["status"] == "dismissed" and done["attempts"] == 1
    assert group.completions() == []
