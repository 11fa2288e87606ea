"""Nothing accepted is lost: a server killed (SIGKILL) or stopped (SIGTERM) while a job runs is
started again over the same data directory, and the job completes.

The job's registration first spends 3 s in 'matching' (progress every 50 ms) and then runs the
real registration, so the server can be killed while the job is running.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path

from tests.service.helpers import Pair, Server, submit, wait_for

ENV = {
    "PWLREG_WORKERS": "1",
    "PWLREG_RUNNER": "tests.service.runners:slow_register",
    "PWLREG_TEST_SLOW_SECONDS": "3",
    "PWLREG_LEASE_SECONDS": "2",
    "PWLREG_PROGRESS_INTERVAL": "0.1",
}


def _row(data_dir: Path, job_id: str) -> tuple[str, int]:
    with sqlite3.connect(data_dir / "pwlreg.db") as db:
        return db.execute("SELECT status, attempts FROM jobs WHERE id = ?", (job_id,)).fetchone()


def _wait_gone(pids: list[int], timeout: float) -> list[int]:
    deadline = time.monotonic() + timeout
    alive = pids
    while alive and time.monotonic() < deadline:
        alive = [p for p in alive if os.path.exists(f"/proc/{p}")
                 and "zombie" not in _state(p)]
        time.sleep(0.05)
    return alive


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:")[1].split("\n")[0].lower()
    except (OSError, IndexError):
        return "gone"


def test_jobs_survive_a_killed_and_a_stopped_server(
    start_server: Callable[..., Server], pair: Pair
) -> None:
    first = start_server(**ENV)
    data_dir = first.data_dir
    with first.client() as client:
        killed_job = submit(client, pair).json()["id"]
        wait_for(client, killed_job, lambda j: j["status"] == "running" and j["progress"] > 0)
    workers = first.children()
    assert workers, "the server has no worker processes"
    first.kill()
    # The workers follow their parent instead of running on as orphans.
    assert _wait_gone(workers, timeout=10) == []
    assert _row(data_dir, killed_job) == ("running", 1)  # the dead attempt still holds the row

    second = start_server(data_dir=data_dir, **ENV)
    with second.client() as client:
        done = wait_for(client, killed_job, timeout=40)
        assert done["status"] == "successful", done
        assert done["attempts"] == 2
        assert client.get(f"/v1/jobs/{killed_job}/mesh").status_code == 200

        stopped_job = submit(client, pair).json()["id"]
        wait_for(client, stopped_job, lambda j: j["status"] == "running" and j["progress"] > 0)
    second.stop()  # graceful: the worker gives the job back without using up an attempt
    assert _row(data_dir, stopped_job) == ("accepted", 0)

    third = start_server(data_dir=data_dir, **ENV)
    with third.client() as client:
        done = wait_for(client, stopped_job, timeout=40)
        assert done["status"] == "successful", done
        assert done["attempts"] == 1
        registered = client.get(f"/v1/jobs/{stopped_job}/registered.png")
        assert registered.status_code == 200 and registered.content[:4] == b"\x89PNG"


def test_a_stop_signalled_to_every_process_gives_the_job_back(
    start_server: Callable[..., Server], pair: Pair
) -> None:
    # systemd's default stop (KillMode=control-group) and kill -TERM -PGID signal the workers
    # as well as the service: a worker that died there cost its job an attempt.
    server = start_server(**ENV)
    data_dir = server.data_dir
    with server.client() as client:
        job = submit(client, pair).json()["id"]
        wait_for(client, job, lambda j: j["status"] == "running" and j["progress"] > 0)
    for pid in server.children():
        os.kill(pid, signal.SIGTERM)
    server.stop()
    assert _row(data_dir, job) == ("accepted", 0)


def test_a_job_whose_worker_dies_does_not_take_its_neighbour_with_it(
    start_server: Callable[..., Server], pair: Pair
) -> None:
    # Two workers: a job that kills its process (as a crash inside a native library does)
    # breaks the pool under the job beside it. Both get that attempt back and then run alone,
    # so only the culprit uses up its attempts.
    server = start_server(**{**ENV, "PWLREG_WORKERS": "2", "PWLREG_TEST_SLOW_SECONDS": "2",
                             "PWLREG_RUNNER": "tests.service.runners:crash_register",
                             "PWLREG_MAX_ATTEMPTS": "2"})
    with server.client() as client:
        good = submit(client, pair).json()["id"]
        wait_for(client, good, lambda j: j["status"] == "running")
        culprit = submit(client, pair, options={"seed": 13}).json()["id"]
        culprit_done = wait_for(client, culprit, timeout=60)
        good_done = wait_for(client, good, timeout=60)
    assert culprit_done["status"] == "failed", culprit_done
    assert culprit_done["attempts"] == 2
    assert good_done["status"] == "successful", good_done
    assert good_done["attempts"] == 1  # the attempt the culprit broke was given back
