"""Ready for a shared network: API keys (401), isolation of the clients' jobs (404), per-client
idempotency keys, back-pressure (429 with Retry-After, 507 on a full disk) and the early
refusal of points the registration could not use (422)."""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from sqlalchemy import inspect

from pwlreg.service.auth import load_api_keys
from pwlreg.service.settings import Settings
from pwlreg.service.store import JobStore
from tests.service.helpers import (
    Pair,
    Server,
    assert_problem,
    metric_samples,
    one,
    submit,
    wait_for,
)

ALICE, BOB, CAROL = "alice-key-0001", "bare-key-0002", "carol-key-0003"
JOB_ROUTES = ("", "/mesh", "/registered.png", "/convergence")


def auth(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


def _keys_file(directory: Path) -> Path:
    path = directory / "keys.txt"
    path.write_text(f"# name key\n\ncarol {CAROL}   # the file's client\n")
    return path


@pytest.fixture(scope="module")
def keyed_server(start_server: Callable[..., Server], tmp_path_factory: pytest.TempPathFactory
                 ) -> Server:
    """Keys of alice (name:key), client1 (bare key) and carol (keys file); real registration."""
    keys_file = _keys_file(tmp_path_factory.mktemp("keys"))
    return start_server(PWLREG_API_KEYS=f"alice:{ALICE}, {BOB}",
                        PWLREG_API_KEYS_FILE=str(keys_file))


def as_client(server: Server, key: str) -> httpx.Client:
    """A client sending ``key`` with every request."""
    return httpx.Client(base_url=server.url, timeout=30.0, headers=auth(key))


def _assert_401(response: httpx.Response) -> None:
    doc = assert_problem(response, 401)
    assert doc["type"] == "urn:pwlreg:problem:unauthorized"
    assert response.headers["www-authenticate"] == "Bearer"


# --- keys ----------------------------------------------------------------------------------------


def test_keys_from_the_variable_and_the_file_with_names(tmp_path: Path) -> None:
    settings = Settings(_env_file=None, api_keys=f"alice:{ALICE},{BOB}, other",  # type: ignore[call-arg]
                        api_keys_file=_keys_file(tmp_path))
    keys = load_api_keys(settings)
    assert keys.names == ["alice", "client1", "client2", "carol"]
    assert keys.identify(ALICE) == "alice" and keys.identify(BOB) == "client1"
    assert keys.identify(CAROL) == "carol" and keys.identify("other") == "client2"
    assert keys.identify("alice-key-000") is None and keys.identify("") is None
    assert not load_api_keys(Settings(_env_file=None))  # type: ignore[call-arg]


@pytest.mark.parametrize(
    ("variable", "file_text"),
    [("a:secret-1,a:secret-2", None), ("a:secret-1,b:secret-1", None), ("a:sec ret", None),
     (None, "carol\n"), (None, "carol secret-9 extra\n"), ("bad name:secret-1", None)],
)
def test_malformed_keys_are_refused_without_showing_them(
    tmp_path: Path, variable: str | None, file_text: str | None
) -> None:
    path = None
    if file_text is not None:
        path = tmp_path / "keys.txt"
        path.write_text(file_text)
    settings = Settings(_env_file=None, api_keys=variable, api_keys_file=path)  # type: ignore[call-arg]
    with pytest.raises(ValueError) as err:
        load_api_keys(settings)
    assert "secret" not in str(err.value)


def test_every_endpoint_but_health_needs_a_key(keyed_server: Server, pair: Pair) -> None:
    with keyed_server.client() as client:
        job_id = submit(client, pair, headers=auth(ALICE)).json()["id"]
        for headers in ({}, auth("wrong-key"), {"Authorization": "Basic YWxpY2U6eA=="},
                        {"Authorization": "Bearer"}, {"Authorization": ALICE}):
            _assert_401(submit(client, pair, headers=headers))
            _assert_401(client.get("/v1/jobs", headers=headers))
            for route in JOB_ROUTES:
                _assert_401(client.get(f"/v1/jobs/{job_id}{route}", headers=headers))
            _assert_401(client.delete(f"/v1/jobs/{job_id}", headers=headers))
            _assert_401(client.get("/v1/options", headers=headers))
            _assert_401(client.get("/metrics", headers=headers))
        for path in ("/healthz", "/readyz", "/openapi.json", "/docs"):
            assert client.get(path).status_code == 200, path
        assert client.get("/v1/options", headers=auth(BOB)).status_code == 200
        assert client.get(f"/v1/jobs/{job_id}", headers=auth(ALICE)).status_code == 200
        assert client.delete(f"/v1/jobs/{job_id}", headers=auth(ALICE)).status_code == 204
    assert ALICE not in keyed_server.log() and BOB not in keyed_server.log()


def test_openapi_declares_the_bearer_scheme(keyed_server: Server) -> None:
    doc = httpx.get(f"{keyed_server.url}/openapi.json").json()
    assert doc["components"]["securitySchemes"]["apiKey"]["scheme"] == "bearer"
    assert doc["paths"]["/v1/jobs"]["post"]["security"] == [{"apiKey": []}]
    assert "security" not in doc["paths"]["/healthz"]["get"]


# --- isolation -----------------------------------------------------------------------------------


def test_a_client_sees_only_its_own_jobs(keyed_server: Server, pair: Pair) -> None:
    with as_client(keyed_server, CAROL) as carol, keyed_server.client() as client:
        mine = submit(carol, pair).json()["id"]
        assert wait_for(carol, mine)["status"] == "successful"
        missing = client.get("/v1/jobs/" + "0" * 32, headers=auth(BOB))
        for route in JOB_ROUTES:
            other = client.get(f"/v1/jobs/{mine}{route}", headers=auth(BOB))
            assert_problem(other, 404)
            assert other.json()["type"] == missing.json()["type"]
            assert other.json()["title"] == missing.json()["title"]
            assert client.get(f"/v1/jobs/{mine}{route}", headers=auth(CAROL)).status_code == 200
        listed = client.get("/v1/jobs", headers=auth(BOB)).json()
        assert mine not in [j["id"] for j in listed["jobs"]]
        own = client.get("/v1/jobs", headers=auth(CAROL)).json()
        assert [j["id"] for j in own["jobs"]] == [mine] and own["numberMatched"] == 1
        assert_problem(client.delete(f"/v1/jobs/{mine}", headers=auth(BOB)), 404)
        after = client.get(f"/v1/jobs/{mine}", headers=auth(CAROL)).json()
        assert after["status"] == "successful"


def test_idempotency_keys_are_scoped_per_client(keyed_server: Server, pair: Pair) -> None:
    key = {"Idempotency-Key": "shared-key-1"}
    with keyed_server.client() as client:
        first = submit(client, pair, headers={**auth(ALICE), **key})
        again = submit(client, pair, headers={**auth(ALICE), **key})
        other = submit(client, pair, headers={**auth(BOB), **key})
        assert (first.status_code, again.status_code, other.status_code) == (201, 201, 201)
        assert again.json()["id"] == first.json()["id"]
        assert again.headers["idempotent-replayed"] == "true"
        assert other.json()["id"] != first.json()["id"]
        assert "idempotent-replayed" not in other.headers
        assert client.get(f"/v1/jobs/{other.json()['id']}", headers=auth(BOB)).status_code == 200
        for response, key_ in ((first, ALICE), (other, BOB)):
            client.delete(f"/v1/jobs/{response.json()['id']}", headers=auth(key_))


def test_old_database_gets_the_owner_column(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'old.db'}"
    store = JobStore.from_url(url)
    store.create_schema()
    store.create("old", {}, False, 3)
    store.dispose()
    with sqlite3.connect(tmp_path / "old.db") as db:  # as an earlier version made it
        db.execute("DROP TABLE alembic_version")  # releases before migrations had neither
        db.execute("ALTER TABLE jobs DROP COLUMN dispatched")
        db.execute("DROP INDEX ix_jobs_owner_status")
        db.execute("ALTER TABLE jobs DROP COLUMN owner")
    store = JobStore.from_url(url)
    store.create_schema()
    try:
        found = inspect(store.engine)
        assert "owner" in {c["name"] for c in found.get_columns("jobs")}
        assert "ix_jobs_owner_status" in {i["name"] for i in found.get_indexes("jobs")}
        old = store.get("old")
        assert old is not None and old.owner is None
        store.create("new", {}, False, 3, owner="alice")
        assert [j.id for j in store.list(owner="alice")[0]] == ["new"]
        assert store.count_accepted() == 2 and store.count_accepted("alice") == 1
    finally:
        store.dispose()


# --- back-pressure ---------------------------------------------------------------------------


def test_the_queue_limit_holds_for_submissions_at_once(start_server: Callable[..., Server],
                                                        pair: Pair) -> None:
    # All of 30 submissions at once passed the queue check while their images were
    # validated: 29 jobs waited under a limit of 5.
    server = start_server(PWLREG_WORKERS="1", PWLREG_RUNNER="tests.service.runners:slow_register",
                          PWLREG_TEST_SLOW_SECONDS="30", PWLREG_MAX_QUEUED_JOBS="3")

    def post(_: int) -> int:
        with server.client() as client:
            return submit(client, pair).status_code

    with ThreadPoolExecutor(max_workers=30) as pool:
        codes = list(pool.map(post, range(30)))
    assert set(codes) == {201, 429}
    with server.client() as client:
        waiting = client.get("/v1/jobs", params={"status": "accepted", "limit": 100}).json()
        listed = client.get("/v1/jobs", params={"limit": 100}).json()
    assert waiting["numberMatched"] <= 3
    # Every job answered 201 is kept (one of them may have started).
    assert listed["numberMatched"] == codes.count(201) <= 4


def test_one_key_sent_at_once_is_one_job_even_on_a_full_queue(
        start_server: Callable[..., Server], pair: Pair) -> None:
    # The first of them fills the queue; the others are its replays, answered whatever the
    # queue, not refused.
    server = start_server(PWLREG_WORKERS="1", PWLREG_RUNNER="tests.service.runners:slow_register",
                          PWLREG_TEST_SLOW_SECONDS="30", PWLREG_MAX_QUEUED_JOBS="1")
    with server.client() as client:
        running = submit(client, pair).json()["id"]
        wait_for(client, running, lambda j: j["status"] == "running")

    def post(_: int) -> httpx.Response:
        with server.client() as client:
            return submit(client, pair, headers={"Idempotency-Key": "once"})

    with ThreadPoolExecutor(max_workers=12) as pool:
        answers = list(pool.map(post, range(12)))
    assert [a.status_code for a in answers] == [201] * 12
    assert len({a.json()["id"] for a in answers}) == 1


def test_a_replay_whose_job_filled_the_queue_since_its_lookup_is_answered(
        tmp_path: Path) -> None:
    # The race the test above ran into once in a few runs: the key not known at the lookup,
    # its job made by another request before the queue's check, which then found it full.
    from types import SimpleNamespace

    from pwlreg.service.api.jobs import _check_queue_unless_replay

    store = JobStore.from_url(f"sqlite:///{tmp_path / 'jobs.db'}")
    store.create_schema()
    lookup = store.get_by_idempotency_key

    def other_request_between(key: str):
        found = lookup(key)
        if key == "once" and found is None:
            store.get_by_idempotency_key = lookup  # one other request
            store.create("b" * 32, {}, False, 1, idempotency_key="once", request_hash="h")
            store.get_by_idempotency_key = other_request_between
        return found

    store.get_by_idempotency_key = other_request_between
    services = SimpleNamespace(store=store, settings=Settings(max_queued_jobs=1, workers=1))
    try:
        _check_queue_unless_replay(services, None, "once")
        with pytest.raises(Exception, match="limit of the service is 1"):
            _check_queue_unless_replay(services, None, "another")
    finally:
        store.dispose()


def test_full_queue_is_429_with_retry_after(start_server: Callable[..., Server],
                                            pair: Pair) -> None:
    server = start_server(
        PWLREG_WORKERS="1",
        PWLREG_RUNNER="tests.service.runners:slow_register",
        PWLREG_TEST_SLOW_SECONDS="30",
        PWLREG_API_KEYS=f"alice:{ALICE},bob:{BOB},carol:{CAROL}",
        PWLREG_MAX_QUEUED_JOBS="2",
        PWLREG_MAX_QUEUED_PER_CLIENT="1",
    )
    jobs: list[tuple[str, str]] = []
    with as_client(server, ALICE) as alice, server.client() as client:
        running = submit(alice, pair).json()["id"]
        jobs.append((running, ALICE))
        wait_for(alice, running, lambda j: j["status"] == "running")
        key = {"Idempotency-Key": "queued-1"}
        queued = submit(client, pair, headers={**auth(ALICE), **key})
        assert queued.status_code == 201
        jobs.append((queued.json()["id"], ALICE))
        # Alice has one job waiting: her limit.
        refused = submit(client, pair, headers=auth(ALICE))
        doc = assert_problem(refused, 429)
        assert doc["type"] == "urn:pwlreg:problem:too-many-jobs"
        assert int(refused.headers["retry-after"]) >= 1
        # A replay of a known key is still answered.
        replay = submit(client, pair, headers={**auth(ALICE), **key})
        assert replay.status_code == 201 and replay.json()["id"] == queued.json()["id"]
        # Bob may queue one; then the service's limit of 2 is reached for everyone.
        bobs = submit(client, pair, headers=auth(BOB))
        assert bobs.status_code == 201, bobs.text
        jobs.append((bobs.json()["id"], BOB))
        full = submit(client, pair, headers=auth(CAROL))
        assert_problem(full, 429)
        assert int(full.headers["retry-after"]) >= 1
        # A refused submission is answered before its body is read.
        assert_problem(client.post("/v1/jobs", headers={**auth(CAROL),
                                   "content-type": "multipart/form-data; boundary=x"},
                                   content=b"x" * 1000), 429)
        # The metrics count the jobs and the refusals per client (a replay is neither).
        samples = metric_samples(client.get("/metrics", headers=auth(BOB)).text)
        submitted, refusals = "pwlreg_jobs_submitted_total", "pwlreg_submissions_refused_total"
        assert one(samples, submitted, client="alice") == 2
        assert one(samples, submitted, client="bob") == 1
        assert one(samples, refusals, client="alice", code="429") == 1
        assert one(samples, refusals, client="carol", code="429") == 2
        for job_id, key_ in jobs:
            assert client.delete(f"/v1/jobs/{job_id}", headers=auth(key_)).status_code == 204


def test_full_disk_is_507_before_the_upload(start_server: Callable[..., Server],
                                            pair: Pair) -> None:
    server = start_server(PWLREG_WORKERS="1", PWLREG_MIN_FREE_BYTES=str(2**62))
    with server.client() as client:
        doc = assert_problem(submit(client, pair), 507)
        assert doc["type"] == "urn:pwlreg:problem:insufficient-storage"
        assert client.get("/v1/jobs").json()["numberMatched"] == 0
        assert client.get("/readyz").status_code == 200


# --- early refusals of points ------------------------------------------------------------------


def _points(reference: list[list[float]], moving: list[list[float]]) -> bytes:
    return json.dumps({"reference": reference, "moving": moving}).encode()


@pytest.mark.parametrize(
    ("points", "detail"),
    [
        (_points([[10, 10], [100, 20]], [[12, 11], [103, 22]]), "at least 3"),
        (_points([[10, 10], [100, 20], [50, 240.6]], [[12, 11], [103, 22], [50, 200]]),
         "outside the 320x240 reference"),
        (_points([[10, 10], [100, 20], [50, 200]], [[12, 11], [103, 22], [-1.6, 200]]),
         "outside the 320x240 moving"),
        (_points([[10, 10], [20, 20], [30, 30], [300, 300 - 70]],
                 [[12, 11], [23, 22], [31, 33], [200, 150]]), None),
        (_points([[10, 10], [20, 20], [30, 30], [40, 40]],
                 [[12, 11], [23, 22], [31, 33], [200, 150]]), "reference points are all collinear"),
        (_points([[10, 10], [100, 20], [50, 200], [200, 100]],
                 [[10, 10], [20, 10], [30, 10], [40, 10]]), "moving points are all collinear"),
        (_points([[10, 10], [10, 10], [50, 200]], [[12, 11], [12, 11], [50, 200]]),
         "collinear (or coincide)"),
    ],
)
def test_unusable_points_are_refused_at_submission(
    server: Server, pair: Pair, points: bytes, detail: str | None
) -> None:
    with server.client() as client:
        response = submit(client, pair, points=points)
        if detail is None:  # in the image within the 1 px tolerance, not collinear: accepted
            assert response.status_code == 201, response.text
            client.delete(f"/v1/jobs/{response.json()['id']}")
            return
    doc = assert_problem(response, 422, field="points")
    assert doc["type"] == "urn:pwlreg:problem:invalid-input"
    assert detail in doc["detail"], doc["detail"]


def test_points_on_the_border_tolerance_are_accepted(server: Server, pair: Pair) -> None:
    points = _points([[-1.4, -1.4], [320.4, 10], [100, 240.4]], [[0, 0], [319, 10], [100, 239]])
    with server.client() as client:
        response = submit(client, pair, points=points)
        assert response.status_code == 201, response.text
        client.delete(f"/v1/jobs/{response.json()['id']}")


def test_the_command_line_sends_the_api_key(keyed_server: Server, pair: Pair,
                                            tmp_path: Path) -> None:
    from tests.service.test_cli import pwlreg

    ref, mov, pts = (tmp_path / n for n in ("r.png", "m.png", "p.json"))
    ref.write_bytes(pair.reference_png)
    mov.write_bytes(pair.moving_png)
    pts.write_bytes(pair.points_json)
    args = ["submit", str(ref), str(mov), "--points", str(pts), "--url", keyed_server.url,
            "--out", str(tmp_path / "out"), "-q", "--optimizer", "none"]
    run = pwlreg(*args)
    assert run.returncode == 1 and "401" in run.stderr
    run = pwlreg(*args, "--api-key", ALICE)
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "out" / "mesh.json").exists()
    assert ALICE not in run.stdout + run.stderr
