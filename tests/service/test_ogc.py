"""OGC API - Processes - Part 1: Core, over real HTTP, answers checked against the standard's
schemas (tests/service/fixtures/ogc, see its README).

A client follows the links from the landing page to the results; inputs are given inline and
by reference to a local file server that the service's allow-list names; a reference to
another origin is refused.
"""

from __future__ import annotations

import asyncio
import base64
import json
import threading
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from functools import cache
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
import yaml
from fastapi import Response
from jsonschema import Draft4Validator
from owslib.ogcapi.processes import Processes
from referencing import Registry, Resource
from referencing.jsonschema import DRAFT4

from pwlreg.core.matching import LISTED_AUTOMATIC
from pwlreg.core.results import RESULTS
from pwlreg.service.app import create_app
from pwlreg.service.hrefs import HrefAllowList, check_href
from pwlreg.service.settings import Settings
from pwlreg.service.webhooks import TargetError
from tests.service.helpers import PROBLEM_TYPE, Pair, Server

SCHEMAS = Path(__file__).parent / "fixtures" / "ogc"
BASE = "https://schemas.opengis.net/ogcapi/processes/part1/1.0/openapi/schemas/"
REL = "http://www.opengis.net/def/rel/ogc/1.0/"
EXCEPTIONS = "http://www.opengis.net/def/exceptions/ogcapi-processes-1/1.0/"
ALICE = {"Authorization": "Bearer key-of-alice"}
BOB = {"Authorization": "Bearer key-of-bob"}
FINISHED = ("successful", "failed", "dismissed")


# --- the standard's schemas -----------------------------------------------------------------


def _retrieve(uri: str) -> Resource:
    name = uri.removeprefix(BASE)
    contents = yaml.safe_load((SCHEMAS / name).read_text())
    return Resource.from_contents(contents, default_specification=DRAFT4)


@cache
def _validator(name: str) -> Draft4Validator:
    return Draft4Validator({"$ref": BASE + name}, registry=Registry(retrieve=_retrieve))


def check(document: Any, schema: str) -> Any:
    """Assert that ``document`` is valid against the OGC schema file ``schema``."""
    errors = sorted(_validator(schema).iter_errors(document), key=lambda e: list(e.path))
    assert not errors, f"not a valid {schema}: " + "; ".join(
        f"{list(e.path)}: {e.message[:200]}" for e in errors[:5])
    return document


def test_the_schemas_reject_what_they_should() -> None:
    # The validation is real: broken documents fail against the same files.
    check({"jobID": "x", "status": "running", "type": "process"}, "statusInfo.yaml")
    for broken in ({"status": "running", "type": "process"},
                   {"jobID": "x", "status": "paused", "type": "process"},
                   {"jobID": "x", "status": "running", "type": "process", "progress": 101},
                   {"jobID": "x", "status": "running", "type": "process",
                    "links": [{"rel": "self"}]}):
        assert list(_validator("statusInfo.yaml").iter_errors(broken)), broken
    assert list(_validator("process.yaml").iter_errors(
        {"id": "p", "version": "1", "inputs": {"a": {"schema": {"exclusiveMinimum": 0}}}}))


# --- servers --------------------------------------------------------------------------------


class Files:
    """A local HTTP server with fixed files (the origin the service may read from)."""

    def __init__(self, files: dict[str, bytes]) -> None:
        self.files = files
        self.requests: list[str] = []
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                owner.requests.append(self.path)
                if self.path == "/slow":
                    time.sleep(3)  # longer than the service's PWLREG_HREF_TIMEOUT
                if self.path == "/redirect":
                    self.send_response(302)
                    self.send_header("Location", "/reference.png")
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                body = owner.files.get(self.path)
                if body is None:
                    self.send_error(404)
                    return
                self.send_response(200)
                if self.path != "/unannounced.png":  # HTTP/1.0: the body ends at the close
                    self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                try:
                    self.wfile.write(body)
                except (BrokenPipeError, ConnectionResetError):
                    pass  # the service hung up on a body over its limit, as it should

            def log_message(self, *args: Any) -> None:
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.httpd.server_address[1]
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def url(self, path: str, host: str = "127.0.0.1") -> str:
        return f"http://{host}:{self.port}{path}"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture(scope="module")
def files(pair: Pair) -> Iterator[Files]:
    server = Files({
        "/reference.png": pair.reference_png,
        "/moving.png": pair.moving_png,
        "/points.json": pair.points_json,
        "/big.png": pair.reference_png + bytes(500 * 1024),  # over the 400 KiB limit
        "/unannounced.png": pair.reference_png + bytes(500 * 1024),
        "/slow": pair.reference_png,
    })
    yield server
    server.close()


@pytest.fixture(scope="module")
def ogc(start_server: Callable[..., Server], files: Files) -> Server:
    """A server with two clients' keys that reads inputs from the local file server, with one
    worker (a registration compiles its kernels once per worker process)."""
    return start_server(
        PWLREG_WORKERS="1",
        PWLREG_API_KEYS="alice:key-of-alice,bob:key-of-bob",
        PWLREG_HREF_ALLOW=f"http://127.0.0.1:{files.port}",
        PWLREG_HREF_TIMEOUT="1",
    )


# --- helpers --------------------------------------------------------------------------------


def link(document: dict[str, Any], rel: str) -> dict[str, Any]:
    found = [li for li in document["links"] if li.get("rel") == rel]
    assert len(found) == 1, (rel, document["links"])
    return found[0]


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def inline_request(pair: Pair, **inputs: Any) -> dict[str, Any]:
    return {"inputs": {
        "reference": {"value": b64(pair.reference_png), "mediaType": "image/png"},
        "moving": {"value": b64(pair.moving_png), "mediaType": "image/png"},
        "points": json.loads(pair.points_json),
        "options": {"bins": 16},
        **inputs,
    }}


def execute(client: httpx.Client, body: Any, headers: dict[str, str] | None = None
            ) -> httpx.Response:
    return client.post("/processes/pwl-registration/execution", json=body,
                       headers={**ALICE, "Prefer": "respond-async", **(headers or {})})


def ogc_problem(response: httpx.Response, status: int, kind: str | None = None,
                field: str | None = None) -> dict[str, Any]:
    """Check an error answer: status, problem+json, exception.yaml, type and field."""
    assert response.status_code == status, (response.status_code, response.text)
    assert response.headers["content-type"].startswith(PROBLEM_TYPE)
    doc = check(response.json(), "exception.yaml")
    if kind is not None:
        assert doc["type"] == kind, doc
    if field is not None:
        assert doc.get("field") == field, doc
    return doc


def wait(client: httpx.Client, href: str, timeout: float = 30.0,
         headers: dict[str, str] = ALICE) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        response = client.get(href, headers=headers)
        assert response.status_code == 200, response.text
        status = check(response.json(), "statusInfo.yaml")
        if status["status"] in FINISHED or time.monotonic() > deadline:
            return status
        time.sleep(0.05)


# --- the client flow --------------------------------------------------------------------------


def test_client_follows_the_links_from_the_landing_page_to_the_results(
    ogc: Server, files: Files, pair: Pair
) -> None:
    with ogc.client() as client:
        landing = client.get("/", headers={**ALICE, "Accept": "application/json"})
        assert landing.status_code == 200, landing.text
        assert landing.headers["content-type"] == "application/json"
        landing_doc = check(landing.json(), "landingPage.yaml")
        assert client.get(link(landing_doc, "service-desc")["href"]).status_code == 200

        conformance = client.get(link(landing_doc, f"{REL}conformance")["href"], headers=ALICE)
        classes = check(conformance.json(), "confClasses.yaml")["conformsTo"]
        assert "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/core" in classes
        assert "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/dismiss" in classes
        assert "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/job-list" in classes

        processes = client.get(link(landing_doc, f"{REL}processes")["href"], headers=ALICE)
        summaries = check(processes.json(), "processList.yaml")["processes"]
        assert [p["id"] for p in summaries] == ["pwl-registration"]
        assert summaries[0]["jobControlOptions"] == ["sync-execute", "async-execute", "dismiss"]

        description = client.get(link(summaries[0], "self")["href"], headers=ALICE)
        process = check(description.json(), "process.yaml")
        assert set(process["inputs"]) == {"reference", "moving", "points", "options"}
        assert [process["inputs"][n]["minOccurs"] for n in process["inputs"]] == [1, 1, 0, 0]
        assert list(process["outputs"]) == list(RESULTS)  # generated from core.results
        for name, output in process["outputs"].items():
            assert output["schema"]["contentMediaType"] == RESULTS[name].media_type
        assert process["inputs"]["options"]["schema"]["properties"]["bins"]["maximum"] == 256

        # Inputs inline (qualified values: the reference in base64, points and options as
        # JSON objects) and by reference (moving, read from the allow-listed file server).
        # The request is not checked against execute.yaml: in 1.0 a string value matches two
        # branches of a oneOf (`type: string` and binaryInputValue), so no string validates.
        body = inline_request(
            pair,
            moving={"href": files.url("/moving.png"), "type": "image/png"},
            points={"value": json.loads(pair.points_json), "mediaType": "application/json"},
            options={"value": {"bins": 16}, "mediaType": "application/json"},
        )
        body["response"] = "document"
        created = client.post(link(process, f"{REL}execute")["href"], json=body,
                              headers={**ALICE, "Prefer": "respond-async"})
        assert created.status_code == 201, created.text
        assert created.headers["preference-applied"] == "respond-async"
        status = check(created.json(), "statusInfo.yaml")
        assert status["status"] in ("accepted", "running")
        assert status["processID"] == "pwl-registration"
        assert created.headers["location"] == link(status, "self")["href"]
        assert "/moving.png" in files.requests

        status = wait(client, created.headers["location"])
        assert status["status"] == "successful", status
        assert status["progress"] == 100 and status["finished"]
        full = client.get(link(status, "alternate")["href"], headers=ALICE).json()
        assert full["id"] == status["jobID"] and full["has_points"] is True
        assert full["options"]["bins"] == 16

        results = client.get(link(status, f"{REL}results")["href"], headers=ALICE)
        assert results.status_code == 200, results.text
        outputs = check(results.json(), "results.yaml")
        assert {"mesh", "registered", "convergence"} <= set(outputs) <= set(RESULTS)
        for name, ref in outputs.items():
            assert ref["type"] == RESULTS[name].media_type
            download = client.get(ref["href"], headers=ALICE)
            assert download.status_code == 200, (name, download.text)
            assert download.headers["content-type"].startswith(RESULTS[name].media_type)
        png = client.get(outputs["registered"]["href"], headers=ALICE).content
        assert png.startswith(b"\x89PNG\r\n\x1a\n")
        mesh = client.get(outputs["mesh"]["href"], headers=ALICE).json()
        assert len(mesh["reference_vertices"]) >= len(pair.reference_points)  # + the border

        job_list = client.get(link(landing_doc, f"{REL}job-list")["href"], headers=ALICE)
        listed = check(job_list.json(), "jobList.yaml")["jobs"]
        assert status["jobID"] in [j["jobID"] for j in listed]


def test_owslib_speaks_to_the_service(ogc: Server, pair: Pair) -> None:
    # OWSLib builds the paths itself (no links); it covers what it implements of Processes.
    api = Processes(ogc.url, headers=ALICE)
    assert {li["rel"] for li in api.links} >= {f"{REL}conformance", f"{REL}processes"}
    assert "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/core" in (
        api.conformance()["conformsTo"])
    assert [p["id"] for p in api.processes()] == ["pwl-registration"]
    assert set(api.process("pwl-registration")["inputs"]) == {"reference", "moving", "points",
                                                               "options"}
    status = api.execute("pwl-registration", inline_request(pair)["inputs"], async_=True)
    check(status, "statusInfo.yaml")
    assert api.response_headers["Location"] == f"/jobs/{status['jobID']}"
    with ogc.client() as client:
        assert wait(client, f"/jobs/{status['jobID']}")["status"] == "successful"


def test_points_and_both_images_by_reference_and_the_same_job_for_the_same_key(
    ogc: Server, files: Files, pair: Pair
) -> None:
    body = {"inputs": {
        "reference": {"href": files.url("/reference.png")},
        "moving": {"href": files.url("/moving.png")},
        "points": {"href": files.url("/points.json"), "type": "application/json"},
    }}
    with ogc.client() as client:
        first = execute(client, body, {"Idempotency-Key": "ogc-1"})
        assert first.status_code == 201, first.text
        again = execute(client, body, {"Idempotency-Key": "ogc-1"})
        assert again.status_code == 201 and again.headers["idempotent-replayed"] == "true"
        assert again.json()["jobID"] == first.json()["jobID"]
        status = wait(client, first.headers["location"])
        assert status["status"] == "successful", status
        full = client.get(link(status, "alternate")["href"], headers=ALICE).json()
        assert full["has_points"] is True


# --- synchronous execution ----------------------------------------------------------------------


def monitor(response: httpx.Response) -> str:
    """The job of a synchronous answer, from its ``Link: <...>; rel="monitor"`` header."""
    href, rel = response.headers["link"].split(";")
    assert rel.strip() == 'rel="monitor"', response.headers["link"]
    return href.strip().removeprefix("<").removesuffix(">")


def test_without_prefer_the_execution_is_synchronous_and_lists_the_dropped_points(
    ogc: Server, pair: Pair
) -> None:
    # A client pair the validation drops: a reference point given twice (the service refuses
    # points outside the images before any job).
    points = json.loads(pair.points_json)
    points["reference"].append(points["reference"][3])
    points["moving"].append([50.0, 50.0])
    with ogc.client() as client:
        answer = client.post("/processes/pwl-registration/execution",
                             json=inline_request(pair, points=points), headers=ALICE)
        assert answer.status_code == 200, answer.text
        assert answer.headers["content-type"] == "application/json"
        assert "location" not in answer.headers and "preference-applied" not in answer.headers
        outputs = check(answer.json(), "results.yaml")
        assert {"mesh", "registered", "tiepoints_geojson"} <= set(outputs) <= set(RESULTS)
        job = check(client.get(monitor(answer), headers=ALICE).json(), "statusInfo.yaml")
        assert job["status"] == "successful" and job["progress"] == 100
        assert client.get(link(job, f"{REL}results")["href"], headers=ALICE).json() == outputs
        ties = client.get(outputs["tiepoints_geojson"]["href"], headers=ALICE).json()
        matching = client.get(outputs["mesh"]["href"], headers=ALICE).json()["matching"]
    features = ties["features"]
    kept = [f for f in features if f["properties"]["kept"]]
    dropped = [f for f in features if not f["properties"]["kept"]]
    assert len(kept) == len(matching["reference"]) and ties["source"] == "client"
    assert [f["id"] for f in features] == list(range(len(features)))
    assert {f["properties"]["reason"] for f in kept} == {None}
    by_reason = {(f["properties"]["reason"], tuple(f["properties"]["reference_px"]),
                  tuple(f["properties"]["moving_px"])) for f in dropped}
    assert ("duplicate", tuple(round(x, 4) for x in points["reference"][3]), (50.0, 50.0)) in (
        by_reason), by_reason
    for feature in dropped:
        assert feature["properties"]["status"] == "dropped"
        # Pixels of the reference: the geometry is where the pair is in the reference.
        assert feature["geometry"]["coordinates"] == feature["properties"]["reference_px"]
        if feature["properties"]["reason"] != "epipolar":
            assert feature["properties"]["residual_px"] is None
    counted = {k: v for k, v in ties["dropped"].items() if v}
    assert counted == {k: v for k, v in matching["rejected"].items() if v}
    reasons = [f["properties"]["reason"] for f in dropped]
    assert counted == {r: reasons.count(r) for r in set(reasons)}  # all listed, one by one


def test_automatic_points_list_every_dropped_pair_with_its_cause(ogc: Server, pair: Pair
                                                                   ) -> None:
    body = inline_request(pair)
    del body["inputs"]["points"]
    with ogc.client() as client:
        created = execute(client, body)
        assert created.status_code == 201, created.text
        status = wait(client, created.headers["location"], timeout=90)
        assert status["status"] == "successful", status
        outputs = client.get(link(status, f"{REL}results")["href"], headers=ALICE).json()
        ties = client.get(outputs["tiepoints_geojson"]["href"], headers=ALICE).json()
        matching = client.get(outputs["mesh"]["href"], headers=ALICE).json()["matching"]
    assert ties["source"] in ("lk", "sift")
    dropped = [f["properties"] for f in ties["features"] if not f["properties"]["kept"]]
    kept = [f["properties"] for f in ties["features"] if f["properties"]["kept"]]
    assert [k["reference_px"] for k in kept] == [[round(x, 4) for x in p]
                                                 for p in matching["reference"]]
    listed = LISTED_AUTOMATIC
    expected = {k: v for k, v in matching["rejected"].items() if k in listed and v}
    assert expected  # the matcher dropped pairs: the test sees some
    reasons = [d["reason"] for d in dropped]
    assert {r: reasons.count(r) for r in set(reasons)} == expected
    for d in dropped:
        judged = d["reason"] in ("epipolar", "neighbours", "spread")
        assert (d["residual_px"] is not None) == judged, d
    # Every pair the matcher found consistent is in the file, kept or dropped.
    assert len(kept) + len(dropped) == matching["counts"]["consistent"]


def test_a_longer_synchronous_execution_answers_the_job(slow_server: Server, pair: Pair
                                                         ) -> None:
    # The slow runner spends 30 s before registering: longer than the client's wait.
    with slow_server.client() as client:
        started = time.monotonic()
        answer = client.post("/processes/pwl-registration/execution", json=inline_request(pair),
                             headers={"Prefer": "wait=1"})
        elapsed = time.monotonic() - started
        assert answer.status_code == 201, answer.text
        assert 1.0 <= elapsed < 10.0
        assert answer.headers["preference-applied"] == "respond-async, wait=1"
        status = check(answer.json(), "statusInfo.yaml")
        assert status["status"] in ("accepted", "running")
        assert answer.headers["location"] == link(status, "self")["href"]
        # Nothing is lost: the job is there and runs on (dismissed here to free the worker).
        later = client.get(answer.headers["location"]).json()
        assert later["jobID"] == status["jobID"] and later["status"] in ("accepted", "running")
        assert client.delete(answer.headers["location"]).status_code == 200


def test_a_client_that_stops_waiting_loses_no_job(slow_server: Server, pair: Pair) -> None:
    key = {"Idempotency-Key": "sync-hang-up"}
    with httpx.Client(base_url=slow_server.url, timeout=1.0) as impatient:
        with pytest.raises(httpx.ReadTimeout):
            impatient.post("/processes/pwl-registration/execution", json=inline_request(pair),
                           headers=key)
    with slow_server.client() as client:
        # The same request again finds the job the first one created, queued or running.
        again = client.post("/processes/pwl-registration/execution",
                            json=inline_request(pair), headers={**key, "Prefer": "respond-async"})
        assert again.status_code == 201 and again.headers["idempotent-replayed"] == "true"
        assert again.json()["status"] in ("accepted", "running")
        assert client.delete(again.headers["location"]).status_code == 200


def test_a_failed_synchronous_execution_answers_its_error_and_the_job(ogc: Server) -> None:
    flat = b64(cv2.imencode(".png", np.full((64, 64), 128, np.uint8))[1].tobytes())
    with ogc.client() as client:
        answer = client.post("/processes/pwl-registration/execution",
                             json={"inputs": {"reference": flat, "moving": flat}},
                             headers={**ALICE, "Prefer": "wait=15"})
        doc = ogc_problem(answer, 422)
        assert doc["type"].endswith("registration-failed")
        assert answer.headers["preference-applied"] == "wait=15"
        job = client.get(monitor(answer), headers=ALICE).json()
        assert job["status"] == "failed" and job["jobID"] == doc["job_id"]


# --- the job list --------------------------------------------------------------------------------


def test_job_list_filters_and_pages(ogc: Server, pair: Pair) -> None:
    # Bob's jobs: one of each final status, made here (the other tests submit as Alice).
    flat = b64(cv2.imencode(".png", np.full((64, 64), 128, np.uint8))[1].tobytes())
    with ogc.client() as client:
        ids: dict[str, str] = {}
        for status, body in (
            ("failed", {"inputs": {"reference": flat, "moving": flat}}),
            ("dismissed", inline_request(pair, options={"optimizer": "none"})),
            ("successful", inline_request(pair, options={"optimizer": "none"})),
        ):
            created = execute(client, body, BOB)
            assert created.status_code == 201, created.text
            ids[status] = created.json()["jobID"]
            if status == "dismissed":
                assert client.delete(created.headers["location"], headers=BOB).is_success
            assert wait(client, created.headers["location"], headers=BOB)["status"] == status

        def listed(query: str | dict[str, Any]) -> list[str]:
            answer = client.get("/jobs", params=query, headers=BOB)
            assert answer.status_code == 200, answer.text
            doc = check(answer.json(), "jobList.yaml")
            assert link(doc, "self")["href"].startswith("/jobs?")
            return [j["jobID"] for j in doc["jobs"]]

        newest_first = [ids["successful"], ids["dismissed"], ids["failed"]]
        assert listed("") == newest_first
        assert listed("status=successful") == [ids["successful"]]
        assert listed("status=failed&status=dismissed") == [ids["dismissed"], ids["failed"]]
        assert listed("status=running") == []
        assert listed("processID=pwl-registration") == newest_first
        assert listed("processID=other&processID=pwl-registration") == newest_first
        assert listed("processID=other") == []
        assert listed("type=process") == newest_first
        assert listed("type=other") == []
        assert listed("type=process&processID=pwl-registration&status=failed") == [ids["failed"]]

        # Pages of one, following the next links; the filters stay in them.
        for query, expected in (("limit=1", newest_first),
                                ("limit=1&status=failed&status=successful",
                                 [ids["successful"], ids["failed"]])):
            seen, href = [], f"/jobs?{query}"
            while href:
                page = check(client.get(href, headers=BOB).json(), "jobList.yaml")
                assert len(page["jobs"]) <= 1
                seen += [j["jobID"] for j in page["jobs"]]
                following = [li for li in page["links"] if li["rel"] == "next"]
                href = following[0]["href"] if following else None
            assert seen == expected, query

        # Creation time: an instant, or an interval with both ends included.
        jobs = {s: client.get(f"/jobs/{i}", headers=BOB).json() for s, i in ids.items()}
        middle = jobs["dismissed"]["created"]
        assert listed({"datetime": f"{middle}/.."}) == newest_first[:2]
        assert listed({"datetime": f"/{middle}"}) == newest_first[1:]
        assert listed({"datetime": f"{middle}/{middle}"}) == [ids["dismissed"]]
        assert listed({"datetime": middle, "status": "dismissed"}) == [ids["dismissed"]]
        assert listed({"datetime": middle, "status": "failed"}) == []
        assert listed({"datetime": f"{jobs['failed']['created']}/{middle}", "limit": 1}) == [
            ids["dismissed"]]
        assert listed({"datetime": "2000-01-01T00:00:00+01:00/2001-01-01T00:00:00Z"}) == []
        # Duration (finished - started): the two jobs that ran took well under an hour; a job
        # that never started has none.
        ran = {s for s, j in jobs.items() if j.get("started") and j.get("finished")}
        assert {"successful", "failed"} <= ran
        assert set(listed({"minDuration": 0})) == {ids[s] for s in ran}
        assert listed({"maxDuration": 3600, "status": "successful"}) == [ids["successful"]]
        assert listed({"minDuration": 3600}) == []
        assert listed({"minDuration": 0, "status": "accepted"}) == []
        took = (datetime.fromisoformat(jobs["successful"]["finished"])
                - datetime.fromisoformat(jobs["successful"]["started"])).total_seconds()
        assert listed({"minDuration": int(took), "maxDuration": int(took) + 1,
                       "status": "successful"}) == [ids["successful"]]
        seen, href = [], "/jobs?limit=1&minDuration=0&status=successful&status=failed"
        while href:  # the next links keep the duration
            page = check(client.get(href, headers=BOB).json(), "jobList.yaml")
            seen += [j["jobID"] for j in page["jobs"]]
            href = next((li["href"] for li in page["links"] if li["rel"] == "next"), None)
        assert seen == [ids["successful"], ids["failed"]]

        for bad in ("status=paused", "limit=0", "limit=10001", "limit=x", "minDuration=-1",
                    "datetime=yesterday", "datetime=../..", "datetime=2026-01-01",
                    f"datetime={jobs['failed']['created']}/2000-01-01T00:00:00Z",
                    "datetime=2026-01-01T00:00:00Z/2026-01-02T00:00:00Z/2026-01-03T00:00:00Z"):
            ogc_problem(client.get(f"/jobs?{bad}", headers=BOB), 422)


def test_filtered_pages_are_read_from_the_store_in_batches() -> None:
    # The datetime and duration filters select in the API, reading SCAN_PAGE jobs at a time:
    # the pages must be those of the filtered list, across batches, and stop at `since`.
    from types import SimpleNamespace

    from pwlreg.service.api.ogc import SCAN_PAGE, _scan

    base = datetime(2026, 1, 1, tzinfo=UTC)
    jobs = [SimpleNamespace(n=n, created=base - timedelta(minutes=n))
            for n in range(3 * SCAN_PAGE)]  # newest first
    reads: list[int] = []

    def read(statuses: Any, limit: int, offset: int, owner: Any) -> tuple[list[Any], int]:
        reads.append(offset)
        return jobs[offset:offset + limit], len(jobs)

    services = SimpleNamespace(store=SimpleNamespace(list=read))
    selected = [j for j in jobs if j.n % 3 == 0]
    for offset, limit in ((0, 10), (160, 7), (330, 20), (480, 20), (495, 10)):
        page, more = _scan(services, [], None, lambda j: j.n % 3 == 0, None, limit, offset)
        assert page == selected[offset:offset + limit]
        assert more == (offset + limit < len(selected)), (offset, limit)
    reads.clear()
    since = jobs[SCAN_PAGE + 10].created
    page, more = _scan(services, [], None, lambda j: j.n % 2 == 0, since, 1000, 0)
    assert page == [j for j in jobs[:SCAN_PAGE + 11] if j.n % 2 == 0] and not more
    assert reads == [0, SCAN_PAGE]  # nothing older than `since` was read past its batch


# --- refusals -----------------------------------------------------------------------------------


def test_href_outside_the_allow_list_is_refused_naming_the_input(
    ogc: Server, files: Files, pair: Pair
) -> None:
    with ogc.client() as client:
        before = len(files.requests)
        # Same server, but an origin (host name) the allow-list does not name.
        refused = execute(client, inline_request(
            pair, moving={"href": files.url("/moving.png", host="localhost")}))
        doc = ogc_problem(refused, 422, field="inputs.moving")
        assert "not among the origins" in doc["detail"]
        for href in ("file:///etc/passwd", "http://169.254.169.254/latest/meta-data/",
                     f"ftp://127.0.0.1:{files.port}/moving.png"):
            ogc_problem(execute(client, inline_request(pair, reference={"href": href})), 422,
                        field="inputs.reference")
        assert len(files.requests) == before  # nothing was read

        missing = execute(client, inline_request(pair, moving={"href": files.url("/nope.png")}))
        assert "HTTP 404" in ogc_problem(missing, 422, field="inputs.moving")["detail"]
        redirect = execute(client, inline_request(pair, moving={"href": files.url("/redirect")}))
        assert "not followed" in ogc_problem(redirect, 422, field="inputs.moving")["detail"]
        for path in ("/big.png", "/unannounced.png"):  # refused by its length, or while read
            big = execute(client, inline_request(pair, reference={"href": files.url(path)}))
            ogc_problem(big, 413, field="inputs.reference")
        slow = execute(client, inline_request(pair, reference={"href": files.url("/slow")}))
        assert "longer than 1 s" in ogc_problem(slow, 422, field="inputs.reference")["detail"]


def test_bad_inputs_are_problems_naming_the_input(ogc: Server, pair: Pair) -> None:
    with ogc.client() as client:
        cases = [
            (inline_request(pair, reference={"value": "not base64!", "mediaType": "image/png"}),
             422, "inputs.reference"),
            (inline_request(pair, moving={"value": b64(pair.moving_png),
                                          "mediaType": "text/plain"}), 415, "inputs.moving"),
            (inline_request(pair, moving={"value": b64(b"GIF89a not really")}), 415,
             "inputs.moving"),
            (inline_request(pair, options={"bins": 1000}), 422, "inputs.options.bins"),
            (inline_request(pair, options={"colour": 1}), 422, "inputs.options.colour"),
            (inline_request(pair, points={"reference": [[1, 1], [2, 2]],
                                          "moving": [[1, 1], [2, 2]]}), 422, "inputs.points"),
            (inline_request(pair, options=5), 422, "inputs.options"),
            (inline_request(pair, points={"value": "x", "encoding": "gzip"}), 422,
             "inputs.points"),
            (inline_request(pair, extra=1), 422, "inputs.extra"),
            (inline_request(pair, moving=[b64(pair.moving_png)]), 422, "inputs.moving"),
            ({"inputs": {"reference": b64(pair.reference_png)}}, 422, "inputs.moving"),
            ({**inline_request(pair), "response": "raw"}, 422, "response"),
            ({**inline_request(pair), "outputs": {"mesh": {"transmissionMode": "value"}}}, 422,
             "outputs.mesh.transmissionMode"),
            ({**inline_request(pair), "outputs": {"nothing": {}}}, 422, "outputs.nothing"),
        ]
        for body, status, field in cases:
            ogc_problem(execute(client, body), status, field=field)
        not_json = client.post("/processes/pwl-registration/execution", content=b"{}",
                               headers={**ALICE, "Content-Type": "text/plain"})
        ogc_problem(not_json, 415)
        broken = client.post("/processes/pwl-registration/execution", content=b"{",
                             headers={**ALICE, "Content-Type": "application/json"})
        ogc_problem(broken, 400)
        # A bare base64 string is an image too (inputValueNoObject, format byte), and points
        # may be the CSV text of the file contract, as text or in base64.
        for points in ({"value": pair.points_csv().decode(), "mediaType": "text/csv"},
                       {"value": b64(pair.points_csv()), "mediaType": "text/csv",
                        "encoding": "base64"}):
            accepted = execute(client, inline_request(pair, reference=b64(pair.reference_png),
                                                      points=points))
            assert accepted.status_code == 201, accepted.text


def test_exceptions_of_the_standard_and_dismiss(ogc: Server, pair: Pair) -> None:
    with ogc.client() as client:
        ogc_problem(client.get("/processes/nope", headers=ALICE), 404,
                    EXCEPTIONS + "no-such-process")
        ogc_problem(execute_to(client, "/processes/nope/execution", inline_request(pair)), 404,
                    EXCEPTIONS + "no-such-process")
        for path in ("/jobs/0123", "/jobs/0123/results"):
            ogc_problem(client.get(path, headers=ALICE), 404, EXCEPTIONS + "no-such-job")
        ogc_problem(client.delete("/jobs/0123", headers=ALICE), 404, EXCEPTIONS + "no-such-job")

        created = execute(client, inline_request(pair, options={"optimizer": "none"}))
        assert created.status_code == 201, created.text
        job = created.headers["location"]
        dismissed = client.delete(job, headers=ALICE)
        assert dismissed.status_code == 200, dismissed.text
        assert check(dismissed.json(), "statusInfo.yaml")["status"] == "dismissed"
        ogc_problem(client.get(f"{job}/results", headers=ALICE), 404,
                    EXCEPTIONS + "result-not-ready")


def execute_to(client: httpx.Client, path: str, body: Any) -> httpx.Response:
    return client.post(path, json=body, headers=ALICE)


def test_a_failed_job_answers_its_error_for_results(ogc: Server) -> None:
    flat = b64(cv2.imencode(".png", np.full((64, 64), 128, np.uint8))[1].tobytes())
    with ogc.client() as client:
        created = execute(client, {"inputs": {"reference": flat, "moving": flat}})
        assert created.status_code == 201, created.text
        status = wait(client, created.headers["location"])
        assert status["status"] == "failed", status
        assert status["message"]
        results = client.get(f"{created.headers['location']}/results", headers=ALICE)
        doc = ogc_problem(results, results.status_code)
        assert 400 <= results.status_code < 600 and doc["type"].endswith("registration-failed")


def test_keys_and_owners_apply_as_on_v1(ogc: Server, pair: Pair) -> None:
    with ogc.client() as client:
        for path in ("/conformance", "/processes", "/processes/pwl-registration", "/jobs",
                     "/?f=json"):
            assert client.get(path).status_code == 401, path
        ogc_problem(client.post("/processes/pwl-registration/execution",
                                json=inline_request(pair)), 401)
        created = execute(client, inline_request(pair))
        job = created.headers["location"]
        job_id = created.json()["jobID"]
        for method, path in (("GET", job), ("GET", f"{job}/results"), ("DELETE", job)):
            ogc_problem(client.request(method, path, headers=BOB), 404,
                        EXCEPTIONS + "no-such-job")
        assert job_id not in [j["jobID"] for j in client.get("/jobs", headers=BOB).json()["jobs"]]
        assert client.get(f"/v1/jobs/{job_id}", headers=ALICE).status_code == 200


def test_landing_page_is_negotiated(ogc: Server) -> None:
    with ogc.client() as client:
        # A browser gets the HTML page of the app's hook (the viewer), or /docs without one;
        # either way no key is needed and it is not the JSON document.
        for browser in (
            client.get("/", headers={"Accept": "text/html,application/xhtml+xml,*/*;q=0.8"}),
            client.get("/?f=html"),
        ):
            if browser.status_code == 303:
                assert browser.headers["location"] == "/docs"
            else:
                assert browser.status_code == 200, browser.text
                assert browser.headers["content-type"].startswith("text/html")
            assert browser.headers["vary"] == "Accept"
        as_json = client.get("/", headers={**ALICE, "Accept": "application/json, text/html;q=0.5"})
        assert as_json.status_code == 200 and check(as_json.json(), "landingPage.yaml")
        assert client.get("/", headers=ALICE).status_code == 200  # no Accept: JSON
        assert client.get("/?f=json", headers=ALICE).json()["links"]
        ogc_problem(client.get("/?f=xml", headers=ALICE), 422)


# --- the address checks of hrefs (no server) -------------------------------------------------


def test_allowed_names_must_resolve_to_allowed_addresses() -> None:
    by_name = HrefAllowList.parse("http://localhost:8123")
    with pytest.raises(TargetError, match="loopback address 127.0.0.1"):
        asyncio.run(check_href("http://localhost:8123/a.png", by_name))
    both = HrefAllowList.parse("http://localhost:8123, http://127.0.0.1:8123")
    origin, address = asyncio.run(check_href("http://LOCALHOST:8123/a.png", both))
    assert str(address) == "127.0.0.1"
    with pytest.raises(TargetError, match="not among the origins"):
        asyncio.run(check_href("http://127.0.0.1:8124/a.png", both))  # another port
    with pytest.raises(TargetError, match="not among the origins"):
        asyncio.run(check_href("https://127.0.0.1:8123/a.png", both))  # another scheme
    with pytest.raises(TargetError, match="credentials"):
        asyncio.run(check_href("http://u:p@127.0.0.1:8123/a.png", both))
    with pytest.raises(TargetError, match="reads no input"):
        asyncio.run(check_href("http://127.0.0.1:8123/a.png", HrefAllowList.parse(None)))
    assert HrefAllowList.parse("https://data.example.org").origins == HrefAllowList.parse(
        "https://DATA.example.org:443/").origins
    for bad in ("data.example.org", "ftp://x", "http://x/path", "http://u@x"):
        with pytest.raises(ValueError, match="PWLREG_HREF_ALLOW"):
            HrefAllowList.parse(bad)


def test_html_landing_page_without_a_viewer_is_the_api_documentation(tmp_path: Path) -> None:
    # The app's hook decides the HTML answer of /; without one it is a redirect to /docs.
    app = create_app(Settings(data_dir=tmp_path, _env_file=None))  # type: ignore[call-arg]
    app.state.html_landing = lambda request: Response("<p>viewer</p>", media_type="text/html")

    async def get(url: str, **kwargs: Any) -> httpx.Response:
        # httpx's ASGI transport does not run the lifespan: the HTML answer needs no services.
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app),
                                     base_url="http://pwlreg.test") as client:
            return await client.get(url, follow_redirects=False, **kwargs)

    page = asyncio.run(get("/", headers={"Accept": "text/html"}))
    assert page.text == "<p>viewer</p>" and page.headers["vary"] == "Accept"
    del app.state.html_landing
    page = asyncio.run(get("/?f=html"))
    assert page.status_code == 303 and page.headers["location"] == "/docs"
