"""Metrics per client and JSON logs, over real HTTP: a server with API keys and
``PWLREG_LOG_FORMAT=json``."""

from __future__ import annotations

import json
from collections.abc import Callable

import pytest

from tests.service.helpers import (
    Pair,
    Server,
    assert_problem,
    metric_samples,
    one,
    submit,
    wait_for,
)

ALICE = "alice-key-7f3c9b2e51d04a6b"
BOB = "bob-key-0c1d2e3f4a5b6c7d"


@pytest.fixture(scope="module")
def json_server(start_server: Callable[..., Server]) -> Server:
    return start_server(
        log_level="info",
        PWLREG_API_KEYS=f"alice:{ALICE},bob:{BOB}",
        PWLREG_LOG_FORMAT="json",
    )


def _auth(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


def test_metrics_per_client_and_json_logs(json_server: Server, pair: Pair) -> None:
    with json_server.client() as client:
        client.headers.update(_auth(ALICE))
        accepted = submit(client, pair, options={"optimizer": "none"})
        assert accepted.status_code == 201, accepted.text
        job_id = accepted.json()["id"]
        assert_problem(submit(client, pair, headers=_auth("not-a-key")), 401)
        assert_problem(client.post("/v1/jobs", files={"reference": ("r.png", b"x")},
                                   headers=_auth(BOB)), 422)
        job = wait_for(client, job_id, timeout=60.0, interval=0.05)
        assert job["status"] == "successful"

        answer = client.get("/metrics", headers=_auth(BOB))
        assert answer.status_code == 200
        samples = metric_samples(answer.text)  # parses as the Prometheus text format
        assert one(samples, "pwlreg_jobs_submitted_total", client="alice") == 1
        assert one(samples, "pwlreg_jobs_submitted_total", client="bob") == 0
        refused = "pwlreg_submissions_refused_total"
        assert one(samples, refused, client="", code="401") == 1
        assert one(samples, refused, client="bob", code="422") == 1
        assert one(samples, "pwlreg_jobs", status="successful") == 1
        assert one(samples, "pwlreg_job_duration_seconds_count", status="successful") == 1
        for stage in ("matching", "triangulating", "optimizing", "rendering"):
            assert one(samples, "pwlreg_stage_duration_seconds_count", stage=stage) == 1

    lines = [line for line in json_server.log_path.read_text().splitlines() if line.strip()]
    records = [json.loads(line) for line in lines]  # every line is one JSON object
    assert all({"time", "level", "logger", "message"} <= set(r) for r in records)
    mine = [r for r in records if r.get("job_id") == job_id]
    loggers = {r["logger"] for r in mine}
    # The API (accepted, finished) and the worker process (started, successful) said so.
    expected = {"pwlreg.service.api.jobs", "pwlreg.service.worker", "pwlreg.service.app"}
    assert expected <= loggers, mine
    assert all(r.get("client") == "alice" for r in mine), mine
    assert any(r["logger"] == "uvicorn.access" for r in records)  # uvicorn's records too
    text = "\n".join(lines)
    assert ALICE not in text and BOB not in text and "not-a-key" not in text
