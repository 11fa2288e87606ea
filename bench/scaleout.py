"""Throughput of the scale-out mode (Celery workers, Redis, PostgreSQL) against the embedded pool
(prints figures; not a test).

40 jobs (the 1024x768 pair with 500 client points of :mod:`bench.service_speed`) are submitted
at once to

* the embedded service (``pwlreg serve``: SQLite, a local pool of 1 and of 2 processes), and
* the scale-out service (``pwlreg serve`` with ``PWLREG_QUEUE=celery`` on a new PostgreSQL
  database and a Redis queue of its own, and 1, 2 and 4 ``pwlreg worker`` processes of one pool
  process each, as containers of the compose file would be),

and each run prints the throughput (jobs per second, from the first submission to the last end),
the latency of the jobs (submission to end, p50 and p95: the queue wait is most of it) and the
CPU seconds per job of the API process (and of the workers). The target: 2 Celery workers reach
at least 1.8 x the throughput of one. API, workers, Redis, PostgreSQL and this client share the
machine's cores; with more workers than cores, the workers share them too.

Usage::

    python -m bench.scaleout [--jobs 40] [--rounds 1] [--postgres URL] [--redis URL]
                             [--configs embedded-1,embedded-2,celery-1,celery-2,celery-4]

PostgreSQL (user with CREATEDB) and Redis must run; the defaults are the local ones.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import psycopg
import redis

from bench.service_speed import (
    _free_port,
    _timestamp,
    children,
    cpu_seconds,
    make_pair,
    percentile,
    submit,
)

REPO = Path(__file__).resolve().parents[1]
Pair = tuple[bytes, bytes, bytes]


def _env(data_dir: Path, settings: dict[str, str]) -> dict[str, str]:
    return {**os.environ, **settings, "PWLREG_DATA_DIR": str(data_dir),
            "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO),
                                                        os.environ.get("PYTHONPATH")]))}


def _start(argv: list[str], env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as out:
        return subprocess.Popen([sys.executable, "-m", "pwlreg.service.cli", *argv], cwd=REPO,
                                env=env, stdout=out, stderr=subprocess.STDOUT)


def _stop(process: subprocess.Popen[bytes]) -> None:
    process.terminate()
    try:
        process.wait(60)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(10)


@contextmanager
def database(admin: str) -> Iterator[str]:
    """A new PostgreSQL database (its SQLAlchemy URL), dropped afterwards."""
    name = f"pwlreg_bench_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(admin, autocommit=True) as db:
        db.execute(f'CREATE DATABASE "{name}"')
    try:
        yield urlsplit(admin)._replace(scheme="postgresql+psycopg", path=f"/{name}").geturl()
    finally:
        with psycopg.connect(admin, autocommit=True) as db:
            db.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


@contextmanager
def service(tmp: Path, label: str, workers: int, celery: dict[str, str] | None) -> Iterator[
    tuple[str, int, list[int]]
]:
    """The API (and, with ``celery`` settings, ``workers`` Celery workers); yields the URL, the
    API's pid and the pids of the worker main processes (none in embedded mode)."""
    data_dir = tmp / label / "data"
    data_dir.mkdir(parents=True)
    settings = {"PWLREG_WORKERS": str(workers), "PWLREG_WORKER_THREADS": "1", **(celery or {})}
    env = _env(data_dir, settings)
    port = _free_port()
    with ExitStack() as stack:
        api = _start(["serve", "--port", str(port), "--log-level", "warning"], env,
                     data_dir.parent / "api.log")
        stack.callback(_stop, api)
        started = []
        for i in range(workers if celery else 0):
            worker = _start(["worker", "--concurrency", "1", "--log-level", "warning"], env,
                            data_dir.parent / f"worker{i}.log")
            stack.callback(_stop, worker)
            started.append(worker)
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 120
        while True:
            if api.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"service did not start; see {data_dir.parent}")
            try:
                if httpx.get(f"{url}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        yield url, api.pid, [w.pid for w in started]


def run_batch(url: str, api_pid: int, worker_pids: list[int], pair: Pair, n: int,
              warm: int) -> dict[str, float | list[float]]:
    """``warm`` jobs first (every worker process started and warm), then ``n`` jobs submitted
    at once; returns the wall time, the latencies and the CPU seconds per job."""
    with httpx.Client(base_url=url, timeout=120) as client:
        _wait(client, [submit(client, pair) for _ in range(warm)])
        workers = worker_pids + [c for pid in worker_pids or [api_pid] for c in children(pid)]
        api0, workers0 = cpu_seconds(api_pid), sum(map(cpu_seconds, workers))
        submitted: dict[str, float] = {}
        t0 = time.time()
        for _ in range(n):
            job_id = submit(client, pair)
            submitted[job_id] = time.time()
        jobs = _wait(client, list(submitted))
        api, worker_cpu = cpu_seconds(api_pid) - api0, sum(map(cpu_seconds, workers)) - workers0
    ends = {job["id"]: _timestamp(job["finished"]) for job in jobs}
    return {"wall": max(ends.values()) - t0,
            "latency": [ends[job_id] - t for job_id, t in submitted.items()],
            "api": api / n, "workers": worker_cpu / n}


def _wait(client: httpx.Client, ids: list[str]) -> list[dict]:
    """Poll twice a second (the CPU of the polling is taken from the workers) until no job
    waits or runs; returns the jobs, all successful."""
    while client.get("/v1/jobs", params={"status": ["accepted", "running"], "limit": 1}
                     ).json()["numberMatched"]:
        time.sleep(0.5)
    jobs = [client.get(f"/v1/jobs/{job_id}").json() for job_id in ids]
    failed = [job["id"] for job in jobs if job["status"] != "successful"]
    if failed:
        raise RuntimeError(f"jobs not successful: {failed}")
    return jobs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", type=int, default=40, help="jobs submitted at once")
    parser.add_argument("--rounds", type=int, default=1, help="rounds of every configuration")
    parser.add_argument("--postgres", default="postgresql://postgres@127.0.0.1:5432/postgres",
                        help="PostgreSQL URL of a user that may create databases")
    parser.add_argument("--redis", default="redis://127.0.0.1:6379",
                        help="Redis server (database 14 is used, with a queue of its own)")
    parser.add_argument("--configs", default="embedded-1,embedded-2,celery-1,celery-2,celery-4",
                        help="the runs of each round, in this order: mode-workers")
    args = parser.parse_args(argv)
    configurations = [(mode, int(n)) for mode, n in
                      (c.split("-") for c in args.configs.split(","))]

    print("load average at start: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    pair = make_pair()
    print(f"pair: 1024x768, 500 points; {args.jobs} jobs at once; {os.cpu_count()} CPU cores")
    runs: dict[tuple[str, int], list[dict]] = {c: [] for c in configurations}
    broker = f"{args.redis.rstrip('/')}/14"
    with tempfile.TemporaryDirectory(prefix="pwlreg-scaleout-") as tmp:
        for r in range(args.rounds):
            for mode, workers in configurations:
                label = f"{mode}-{workers}-{r}"
                if mode == "embedded":
                    with service(Path(tmp), label, workers, None) as (url, api, pids):
                        runs[mode, workers].append(
                            run_batch(url, api, pids, pair, args.jobs, 2 * workers))
                    continue
                queue = f"pwlreg-bench-{uuid.uuid4().hex[:10]}"
                with database(args.postgres) as db_url, service(Path(tmp), label, workers, {
                    "PWLREG_QUEUE": "celery", "PWLREG_BROKER_URL": broker,
                    "PWLREG_BROKER_QUEUE": queue, "PWLREG_DATABASE_URL": db_url,
                }) as (url, api, pids):
                    runs[mode, workers].append(
                        run_batch(url, api, pids, pair, args.jobs, 2 * workers))
                client = redis.Redis.from_url(broker)
                for key in client.scan_iter(match=f"*{queue}*"):  # the queue, its bindings
                    client.delete(key)
                client.close()

    def median(key: tuple[str, int], name: str) -> float:
        return statistics.median(run[name] for run in runs[key])  # type: ignore[misc]

    print(f"\n{args.jobs} jobs at once, median of {args.rounds} round(s)")
    print(f"  {'':<30} {'jobs/s':>7} {'p50 s':>7} {'p95 s':>7}   CPU ms per job: API  workers")
    for key in configurations:
        mode, workers = key
        label = (f"embedded pool, {workers} process{'es' if workers > 1 else ''}"
                 if mode == "embedded" else f"Celery, {workers} worker{'s' if workers > 1 else ''}")
        latencies = [x for run in runs[key] for x in run["latency"]]  # type: ignore[union-attr]
        print(f"  {label:<30} {args.jobs / median(key, 'wall'):7.2f} "
              f"{percentile(latencies, 50):7.2f} {percentile(latencies, 95):7.2f}   "
              f"{median(key, 'api') * 1000:18.1f} {median(key, 'workers') * 1000:8.1f}")
    for mode, target in (("celery", " (target: 1.8x)"), ("embedded", "")):
        if (mode, 1) not in runs or (mode, 2) not in runs:
            continue
        ratios = [a["wall"] / b["wall"] for a, b in zip(runs[mode, 1], runs[mode, 2],
                                                           strict=True)]
        print(f"throughput {mode} 2 workers / 1: {statistics.median(ratios):.2f}x median"
              f"{target}; rounds: " + ", ".join(f"{x:.2f}" for x in ratios))
    print("load average at end: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
