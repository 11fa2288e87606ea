"""Dismissing jobs over real HTTP: a running job stops at its next check, a queued job never
runs, files are removed; results of an unfinished job are 409.

The slow server has one worker whose registration spends 30 s in 'matching' before the real
registration, so a job is reliably running when it is cancelled.
"""

from __future__ import annotations

import time

from tests.service.helpers import Pair, Server, assert_problem, submit, wait_for


def test_results_of_an_unfinished_job_are_409(slow_server: Server, pair: Pair) -> None:
    with slow_server.client() as client:
        job_id = submit(client, pair).json()["id"]
        try:
            for route in ("mesh", "registered.png", "convergence"):
                doc = assert_problem(client.get(f"/v1/jobs/{job_id}/{route}"), 409)
                assert doc["type"] == "urn:pwlreg:problem:result-not-ready"
                assert doc["job_status"] in ("accepted", "running")
        finally:
            client.delete(f"/v1/jobs/{job_id}")
        doc = assert_problem(client.get(f"/v1/jobs/{job_id}/mesh"), 409)
        assert doc["job_status"] == "dismissed"


def test_cancel_running_and_queued_jobs(slow_server: Server, pair: Pair) -> None:
    with slow_server.client() as client:
        running = submit(client, pair).json()["id"]
        queued = submit(client, pair).json()["id"]  # one worker: waits behind the first
        job = wait_for(client, running, lambda j: j["status"] == "running" and j["progress"] > 0)
        assert job["stage"] == "matching"
        assert client.get(f"/v1/jobs/{queued}").json()["status"] == "accepted"
        job_dir = slow_server.data_dir / "jobs" / running
        assert (job_dir / "inputs" / "reference").is_file()

        # Dismiss the queued job first: it must never start.
        response = client.delete(f"/v1/jobs/{queued}")
        assert response.status_code == 204 and response.content == b""
        t0 = time.monotonic()
        response = client.delete(f"/v1/jobs/{running}")
        assert response.status_code == 204

        doc = client.get(f"/v1/jobs/{running}").json()
        assert doc["status"] == "dismissed" and doc["finished"] is not None
        assert not job_dir.exists()

        # The worker stops at its next progress check (every 50 ms), far before its 30 s of
        # matching: the next job starts on the only worker within seconds.
        after = submit(client, pair, options={"optimizer": "none"}).json()["id"]
        wait_for(client, after, lambda j: j["status"] == "running", timeout=10)
        assert time.monotonic() - t0 < 10
        assert client.get(f"/v1/jobs/{running}").json()["status"] == "dismissed"

        never = client.get(f"/v1/jobs/{queued}").json()
        assert never["status"] == "dismissed"
        assert never["started"] is None and never["attempts"] == 0
        assert not (slow_server.data_dir / "jobs" / queued).exists()

        # Dismissing again is harmless; the job stays listed as dismissed.
        assert client.delete(f"/v1/jobs/{running}").status_code == 204
        listed = client.get("/v1/jobs", params={"status": "dismissed", "limit": 100}).json()
        assert {running, queued} <= {j["id"] for j in listed["jobs"]}
        client.delete(f"/v1/jobs/{after}")
