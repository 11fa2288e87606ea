"""Jobs API over real HTTP: a job from upload to downloaded results, listing, idempotency,
options, health, readiness and metrics."""

from __future__ import annotations

import io
import json
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from datetime import datetime

import numpy as np
from PIL import Image
from prometheus_client import CONTENT_TYPE_LATEST

from pwlreg.core.options import RegistrationOptions
from tests.service.helpers import (
    Pair,
    Server,
    assert_problem,
    make_pair,
    metric_samples,
    one,
    submit,
    wait_for,
)

RESULTS_REL = "http://www.opengis.net/def/rel/ogc/1.0/results"


def test_job_from_upload_to_downloaded_results(server: Server, pair: Pair) -> None:
    with server.client() as client:
        response = submit(client, pair, options={"bins": 24, "epsilon": 0.005})
        assert response.status_code == 201, response.text
        job = response.json()
        assert response.headers["location"] == f"/v1/jobs/{job['id']}"
        assert job["status"] in ("accepted", "running")
        assert job["options"]["bins"] == 24 and job["options"]["epsilon"] == 0.005
        assert job["options"]["cost"] == RegistrationOptions().cost  # defaults filled in
        assert job["has_points"] is True
        assert {"href": f"/v1/jobs/{job['id']}", "rel": "self", "type": "application/json",
                "title": "This job"} in job["links"]

        done = wait_for(client, job["id"])
        assert done["status"] == "successful", done
        assert done["progress"] == 100 and done["stage"] is None
        assert done["attempts"] == 1
        created, started, finished = (
            datetime.fromisoformat(done[k]) for k in ("created", "started", "finished")
        )
        assert created <= started <= finished
        assert done["message"] and "\n" not in done["message"]
        results = {link["href"].rsplit("/", 1)[1]: link for link in done["links"]
                   if link["rel"] == RESULTS_REL}
        assert {k: v["type"] for k, v in results.items()}.items() >= {
            "mesh": "application/json",
            "registered.png": "image/png",
            "convergence": "application/json",
        }.items()
        for link in results.values():  # every result answers HEAD with its headers only
            head = client.head(link["href"])
            assert head.status_code == 200 and head.content == b"", link
            assert head.headers["content-type"].startswith(link["type"])
            assert int(head.headers["content-length"]) > 0

        mesh_response = client.get(results["mesh"]["href"])
        assert mesh_response.status_code == 200
        assert mesh_response.headers["content-type"].startswith("application/json")
        mesh = mesh_response.json()
        for key in ("reference_vertices", "moving_vertices", "initial_triangles",
                    "final_triangles", "swaps", "parameters", "matching"):
            assert key in mesh, key
        assert mesh["parameters"]["bins"] == 24
        # The registration really used our points: moving vertices = affine(reference vertices).
        ref = np.asarray(mesh["reference_vertices"])
        mov = np.asarray(mesh["moving_vertices"])
        assert len(ref) >= 30
        predicted = ref @ pair.affine[:, :2].T + pair.affine[:, 2]
        assert np.abs(predicted - mov).max() < 0.05

        png = client.get(results["registered.png"]["href"])
        assert png.status_code == 200 and png.headers["content-type"] == "image/png"
        image = Image.open(io.BytesIO(png.content))
        assert image.size == (320, 240)
        assert image.mode in ("LA", "RGBA")
        alpha = np.asarray(image)[..., -1]
        assert 0 < (alpha > 0).mean() < 1  # opaque inside the mesh only

        convergence = client.get(results["convergence"]["href"]).json()
        for key in ("initial", "iterations", "final", "stopped_because"):
            assert key in convergence, key
        assert set(convergence["initial"]) >= {"mi", "nmi"}

        # A result this job has no reason to make (no georeferencing): a documented 404.
        assert "registered.tif" not in results
        missing = client.get(f"/v1/jobs/{job['id']}/registered.tif")
        assert missing.status_code == 404
        assert missing.json()["type"] == "urn:pwlreg:problem:not-found"
        assert "registered.tif" in missing.json()["detail"]


def test_points_as_csv_form_field_and_options_as_file_part(server: Server, pair: Pair) -> None:
    files = {
        "reference": ("r.png", pair.reference_png, "image/png"),
        "moving": ("m.png", pair.moving_png, "image/png"),
        "options": ("options.json", json.dumps({"optimizer": "none"}).encode(),
                    "application/json"),
    }
    with server.client() as client:
        response = client.post("/v1/jobs", files=files, data={"points": pair.points_csv()})
        assert response.status_code == 201, response.text
        done = wait_for(client, response.json()["id"])
        assert done["status"] == "successful", done
        assert done["options"]["optimizer"] == "none"
        mesh = client.get(f"/v1/jobs/{done['id']}/mesh").json()
        measured = [not e for e in mesh["extrapolated"]]
        assert len(mesh["reference_vertices"]) == len(mesh["extrapolated"])
        assert sum(measured) == len(pair.reference_points)


def test_job_that_cannot_be_registered_fails_with_a_problem(server: Server, pair: Pair) -> None:
    # Unrelated images without points: nothing to match, found only by the registration (two
    # point pairs, which used to fail here, are now refused at submission: test_access.py).
    unrelated = replace(pair, moving_png=make_pair(seed=99).moving_png)
    with server.client() as client:
        response = submit(client, unrelated, points=None)
        assert response.status_code == 201, response.text
        done = wait_for(client, response.json()["id"])
        assert done["status"] == "failed"
        error = done["error"]
        assert error["type"] == "urn:pwlreg:problem:registration-failed"
        assert error["status"] == 422 and error["field"] == "points"
        assert "point" in error["detail"] and done["message"] == error["detail"]
        assert [link["rel"] for link in done["links"]] == ["self"]
        for route in ("mesh", "registered.png", "convergence"):
            doc = assert_problem(client.get(f"/v1/jobs/{done['id']}/{route}"), 409)
            assert doc["job_status"] == "failed"


def test_list_is_newest_first_paginated_and_filtered(start_server, pair: Pair) -> None:
    # A server of its own, so that the counts are exact.
    own = start_server(PWLREG_WORKERS="1")
    with own.client() as client:
        ids = [submit(client, pair, options={"optimizer": "none"}).json()["id"] for _ in range(5)]
        for job_id in ids:
            wait_for(client, job_id)
        client.delete(f"/v1/jobs/{ids[1]}")

        page = client.get("/v1/jobs", params={"limit": 2}).json()
        assert page["numberMatched"] == 5 and page["numberReturned"] == 2
        assert [j["id"] for j in page["jobs"]] == ids[::-1][:2]
        rels = {link["rel"]: link["href"] for link in page["links"]}
        assert "prev" not in rels
        second = client.get(rels["next"]).json()
        assert [j["id"] for j in second["jobs"]] == ids[::-1][2:4]
        assert "prev" in {link["rel"] for link in second["links"]}
        last = client.get("/v1/jobs", params={"limit": 2, "offset": 4}).json()
        assert [j["id"] for j in last["jobs"]] == [ids[0]]
        assert "next" not in {link["rel"] for link in last["links"]}

        dismissed = client.get("/v1/jobs", params={"status": "dismissed"}).json()
        assert [j["id"] for j in dismissed["jobs"]] == [ids[1]]
        both = client.get("/v1/jobs", params=[("status", "dismissed"),
                                               ("status", "successful")]).json()
        assert both["numberMatched"] == 5
        successful = client.get("/v1/jobs", params={"status": "successful"}).json()
        assert successful["numberMatched"] == 4
        assert all(j["status"] == "successful" for j in successful["jobs"])


def test_idempotency_key_returns_the_same_job(server: Server, pair: Pair) -> None:
    key = f"test-{uuid.uuid4()}"
    with server.client() as client:
        before = client.get("/v1/jobs").json()["numberMatched"]
        first = submit(client, pair, headers={"Idempotency-Key": key})
        second = submit(client, pair, headers={"Idempotency-Key": key})
        assert first.status_code == second.status_code == 201
        assert first.json()["id"] == second.json()["id"]
        assert first.headers["location"] == second.headers["location"]
        assert second.headers.get("idempotent-replayed") == "true"
        assert client.get("/v1/jobs").json()["numberMatched"] == before + 1

        # The same key with another request is refused, not silently answered with the job.
        other = submit(client, pair, options={"bins": 8}, headers={"Idempotency-Key": key})
        doc = assert_problem(other, 422, field="Idempotency-Key")
        assert doc["job_id"] == first.json()["id"]

        # Without a key, the same request makes a new job.
        third = submit(client, pair)
        assert third.json()["id"] != first.json()["id"]


def test_options_lists_every_option_with_default_bounds_and_help(server: Server) -> None:
    with server.client() as client:
        options = client.get("/v1/options").json()
    by_name = {o["name"]: o for o in options}
    assert list(by_name) == list(RegistrationOptions.model_fields)
    for name, field in RegistrationOptions.model_fields.items():
        info = by_name[name]
        assert info["default"] == field.default, name
        assert info["help"] == field.description, name
    assert by_name["bins"]["type"] == "integer"
    assert (by_name["bins"]["minimum"], by_name["bins"]["maximum"]) == (2, 256)
    assert by_name["cost"]["type"] == "string" and by_name["cost"]["choices"] == ["mi", "ncc"]
    assert by_name["epipolar_threshold"]["exclusive_minimum"] == 0
    assert by_name["epipolar_filter"]["type"] == "boolean"


def test_health_readiness_and_metrics(server: Server, pair: Pair) -> None:
    with server.client() as client:
        assert client.get("/healthz").json() == {"status": "ok"}
        ready = client.get("/readyz")
        assert ready.status_code == 200
        assert ready.json()["checks"] == {"database": True, "queue": True, "storage": True}

        job_id = submit(client, pair, options={"optimizer": "none"}).json()["id"]
        wait_for(client, job_id)
        answer = client.get("/metrics")
        assert answer.headers["content-type"] == CONTENT_TYPE_LATEST
        samples = metric_samples(answer.text)
        counts = {labels["status"]: value for labels, value in samples["pwlreg_jobs"]}
        assert set(counts) == {"accepted", "running", "successful", "failed", "dismissed"}
        listed = client.get("/v1/jobs", params={"limit": 1}).json()["numberMatched"]
        assert sum(counts.values()) == listed
        assert counts["successful"] >= 1
        assert samples["pwlreg_queue_depth"][0][1] >= 0
        assert samples["pwlreg_workers"] == [({}, 2.0)]
        # Without API keys the submissions count under the empty client.
        assert one(samples, "pwlreg_jobs_submitted_total", client="") >= 1
        # The job's duration and the seconds of each of its stages, observed when it ended.
        count = one(samples, "pwlreg_job_duration_seconds_count", status="successful")
        assert count >= 1
        assert one(samples, "pwlreg_job_duration_seconds_bucket", status="successful",
                   le="+Inf") == count
        for stage in ("matching", "triangulating", "optimizing", "rendering"):
            assert one(samples, "pwlreg_stage_duration_seconds_count", stage=stage) >= 1
            assert one(samples, "pwlreg_stage_duration_seconds_sum", stage=stage) >= 0


def test_concurrent_requests_with_one_idempotency_key_make_one_job(
    server: Server, pair: Pair
) -> None:
    key = f"race-{uuid.uuid4()}"

    def post(_: int) -> tuple[int, str]:
        with server.client() as client:
            response = submit(client, pair, headers={"Idempotency-Key": key})
            return response.status_code, response.json()["id"]

    with ThreadPoolExecutor(max_workers=6) as pool:
        answers = list(pool.map(post, range(6)))
    assert {status for status, _ in answers} == {201}
    assert len({job_id for _, job_id in answers}) == 1
    with server.client() as client:
        listed = client.get("/v1/jobs", params={"limit": 10}).json()["jobs"]
    assert sum(j["id"] == answers[0][1] for j in listed) == 1  # newest first: it is on top
    # The losers of the race left no files behind.
    assert not any((server.data_dir / "uploads").iterdir())
    with server.client() as client:
        for job_dir in (server.data_dir / "jobs").iterdir():
            assert client.get(f"/v1/jobs/{job_dir.name}").status_code == 200, job_dir
