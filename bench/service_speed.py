"""Speed of the service against the core entry point (prints figures; not a test).

1. Latency: 20 sequential jobs on a 1024x768 pair with 500 client points, submit-to-successful
   (upload, validation, queue, worker, registration, result files, polling every 10 ms), set
   against ``core.pipeline.register`` called directly in this process on the same decoded pair.
   The difference of the medians is the service overhead (target: under 100 ms at p50).
2. Throughput: 40 jobs submitted at once to a service with 1 worker, then with 2 workers
   (target: 2 workers at least 1.8x the jobs per second of 1 worker), with the CPU time per job
   of the API process, the workers and this client; then, as the machine's ceiling, the same
   40 jobs (decode, register, write) in a pool of 1 and of 2 processes calling the core
   directly.

Usage::

    python -m bench.service_speed [--jobs 20] [--batch 40] [--workers 2] [--rounds 3]

The services run as ``python -m pwlreg.service.cli serve`` subprocesses on 127.0.0.1 with their data
directory in a temporary directory.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path

import cv2
import httpx
import numpy as np

from pwlreg.core.io import load_points, read_image
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.pipeline import register
from pwlreg.core.results import write_outputs

REPO = Path(__file__).resolve().parents[1]


def make_pair(width: int = 1024, height: int = 768, n_points: int = 500, seed: int = 3) -> tuple[
    bytes, bytes, bytes
]:
    """A textured reference, a moving image made by an affine plus a smooth sinusoidal warp
    (so that the edge-swap optimizer has work to do), and ``n_points`` exact conjugate points.

    Returns PNG bytes of both images and the points file (JSON, pixel coordinates).
    """
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), 3.0)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)

    def source(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Reference position of the moving pixel (x, y).
        return (0.98 * x + 0.02 * y + 6 + 4 * np.sin(y / 90.0),
                -0.01 * x + 1.01 * y - 4 + 3 * np.sin(x / 120.0))

    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    map_x, map_y = source(xs, ys)
    moving = cv2.remap(texture, map_x.astype(np.float32), map_y.astype(np.float32),
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    moving_pts = np.column_stack([rng.uniform(10, width - 10, n_points),
                                  rng.uniform(10, height - 10, n_points)])
    rx, ry = source(moving_pts[:, 0], moving_pts[:, 1])
    points = {"reference": np.column_stack([rx, ry]).tolist(), "moving": moving_pts.tolist()}
    return (cv2.imencode(".png", texture)[1].tobytes(), cv2.imencode(".png", moving)[1].tobytes(),
            json.dumps(points).encode())


def _timestamp(value: str) -> float:
    return datetime.fromisoformat(value.replace("Z", "+00:00")).timestamp()


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def service(workers: int, data_dir: Path, threads: int = 1) -> Iterator[tuple[str, int]]:
    """A ``pwlreg serve`` subprocess with ``workers`` workers of ``threads`` threads each;
    yields its URL and process id."""
    port = _free_port()
    env = {**os.environ, "PWLREG_DATA_DIR": str(data_dir), "PWLREG_WORKERS": str(workers),
           "PWLREG_WORKER_THREADS": str(threads),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    log = (data_dir.parent / f"server-{workers}.log").open("wb")
    process = subprocess.Popen(
        [sys.executable, "-m", "pwlreg.service.cli", "serve", "--port", str(port), "--log-level",
         "warning"], cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"service did not start; see {log.name}")
            try:
                if httpx.get(f"{url}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        yield url, process.pid
    finally:
        process.terminate()
        process.wait(60)
        log.close()


def submit(client: httpx.Client, pair: tuple[bytes, bytes, bytes]) -> str:
    reference, moving, points = pair
    response = client.post("/v1/jobs", files={
        "reference": ("reference.png", reference, "image/png"),
        "moving": ("moving.png", moving, "image/png"),
        "points": ("points.json", points, "application/json"),
    })
    response.raise_for_status()
    return response.json()["id"]


def run_one(client: httpx.Client, pair: tuple[bytes, bytes, bytes], poll: float = 0.01) -> dict[
    str, float
]:
    """Submit one job and poll it until it is finished.

    Returns the seconds of each phase: ``total`` (submit to seen successful), ``accept`` (the
    POST: upload, checks, storage), ``dispatch`` (accepted to started), ``attempt`` (started to
    finished, in the worker) and ``notice`` (finished to seen by the polling client). Server
    and client share the machine's clock.
    """
    t0 = time.time()
    job_id = submit(client, pair)
    t_accepted = time.time()
    while True:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if job["status"] in ("successful", "failed", "dismissed"):
            t_seen = time.time()
            if job["status"] != "successful":
                raise RuntimeError(f"job {job_id} {job['status']}: {job.get('message')}")
            break
        time.sleep(poll)
    created, started, finished = (_timestamp(job[k]) for k in ("created", "started", "finished"))
    return {
        "total": t_seen - t0,
        "accept": t_accepted - t0,
        "dispatch": started - created,
        "attempt": finished - started,
        "notice": t_seen - finished,
    }


_TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc), 0 once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / _TICKS


def children(pid: int) -> list[int]:
    """Process ids of the direct children of ``pid`` (the worker processes of a service)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(stat[1]) == pid:
                found.append(int(entry.name))
    return found


def run_batch(url: str, pid: int, pair: tuple[bytes, bytes, bytes], n: int) -> dict[str, float]:
    """Submit ``n`` jobs at once and wait for all.

    The batch ends when the last job finished, by the server's ``finished`` timestamps (server
    and client share the machine's clock), so the client polls only twice a second: a poll
    every few milliseconds would be CPU taken from the workers by the measurement itself.

    Returns the wall time (``wall``) and the CPU seconds per job of the API process (``api``),
    of all worker processes together (``workers``) and of this client (``client``: uploads and
    polling).
    """
    with httpx.Client(base_url=url, timeout=120) as client:
        run_one(client, pair)  # warm-up: worker processes started, core imported
        workers = children(pid)
        api0, workers0 = cpu_seconds(pid), sum(map(cpu_seconds, workers))
        client0 = time.process_time()
        t0 = time.time()
        ids = [submit(client, pair) for _ in range(n)]
        while True:
            time.sleep(0.5)
            page = client.get("/v1/jobs", params={"status": ["accepted", "running"],
                                                  "limit": 1}).json()
            if page["numberMatched"] == 0:
                break
        cpu = {"api": cpu_seconds(pid) - api0,
               "workers": sum(map(cpu_seconds, workers)) - workers0,
               "client": time.process_time() - client0}
        jobs = [client.get(f"/v1/jobs/{job_id}").json() for job_id in ids]
    failed = [job["id"] for job in jobs if job["status"] != "successful"]
    if failed:
        raise RuntimeError(f"jobs not successful: {failed}")
    elapsed = max(_timestamp(job["finished"]) for job in jobs) - t0
    return {"wall": elapsed, **{k: v / n for k, v in cpu.items()}}


def _core_init() -> None:
    cv2.setNumThreads(1)
    from pwlreg.core.pipeline import warm_up

    warm_up()


def _core_job(args: tuple[tuple[bytes, bytes, bytes], str]) -> float:
    """What a worker does for one job, without the service: decode, register, write."""
    (reference, moving, points), out = args
    t0 = time.process_time()
    result = register(read_image(reference, field="reference"),
                      read_image(moving, field="moving"), points=load_points(points))
    write_outputs(result, out)
    return time.process_time() - t0


def core_batch(pair: tuple[bytes, bytes, bytes], n: int, processes: int, out: Path) -> dict[
    str, float
]:
    """The control: ``n`` jobs in a pool of ``processes`` single-threaded processes calling the
    core directly (no HTTP, no database). Returns the wall time and the CPU seconds per job."""
    with multiprocessing.get_context("spawn").Pool(processes, initializer=_core_init) as pool:
        pool.map(_core_job, [(pair, str(out / f"warm-{i}")) for i in range(2 * processes)],
                 chunksize=1)
        t0 = time.perf_counter()
        cpu = pool.map(_core_job, [(pair, str(out / f"job-{i}")) for i in range(n)],
                       chunksize=1)
        elapsed = time.perf_counter() - t0
    return {"wall": elapsed, "workers": float(np.mean(cpu))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", type=int, default=20, help="sequential jobs (latency)")
    parser.add_argument("--batch", type=int, default=40,
                        help="jobs at once (throughput); 0 skips the throughput runs")
    parser.add_argument("--workers", type=int, default=2, help="workers of the parallel run")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of the throughput runs")
    args = parser.parse_args(argv)

    print("load average at start: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    pair = make_pair()
    print(f"pair: 1024x768, 500 points; PNGs {len(pair[0]) // 1024} + {len(pair[1]) // 1024} KiB")
    reference = read_image(pair[0], field="reference")
    moving = read_image(pair[1], field="moving")
    points = load_points(pair[2])
    options = RegistrationOptions()

    with tempfile.TemporaryDirectory(prefix="pwlreg-bench-") as tmp:
        tmp_dir = Path(tmp)
        # The core entry point called directly in this process, and the same pair through a
        # service with one worker, one after the other (so that both see the same machine).
        # The worker gets as many threads as the direct call uses (all cores), so that the
        # difference is the service's own work.
        threads = len(os.sched_getaffinity(0))
        direct: list[float] = []
        direct_io: list[float] = []
        direct_all: list[float] = []
        phases: dict[str, list[float]] = {}
        (tmp_dir / "seq").mkdir()
        with service(1, tmp_dir / "seq" / "data", threads) as (url, _), httpx.Client(
            base_url=url, timeout=120
        ) as client:
            register(reference, moving, points=points, options=options)  # warm-up
            run_one(client, pair)  # warm-up
            for i in range(args.jobs):
                t0 = time.perf_counter()
                read_image(pair[0], field="reference"), read_image(pair[1], field="moving")
                t1 = time.perf_counter()
                result = register(reference, moving, points=points, options=options)
                direct.append(time.perf_counter() - t1)
                write_outputs(result, tmp_dir / f"direct-{i}")
                direct_io.append(time.perf_counter() - t1)
                direct_all.append(time.perf_counter() - t0)
                for name, seconds in run_one(client, pair).items():
                    phases.setdefault(name, []).append(seconds)
        print(f"summary: {result.summary()}")

        def row(label: str, values: list[float]) -> None:
            print(f"  {label:<44} {percentile(values, 50) * 1000:8.1f} "
                  f"{percentile(values, 95) * 1000:8.1f}")

        print(f"\nlatency over {args.jobs} jobs, one at a time (ms)          p50      p95")
        row("core register() direct", direct)
        row("register() + write_outputs() direct", direct_io)
        row("decode + register() + write_outputs() direct", direct_all)
        row(f"service (1 worker, {threads} threads): submit to seen", phases["total"])
        row("  POST: upload, check, store", phases["accept"])
        row("  accepted to started (queue)", phases["dispatch"])
        row("  started to finished (worker)", phases["attempt"])
        row("  finished to seen (polling every 10 ms)", phases["notice"])
        overhead = (statistics.median(phases["total"]) - statistics.median(direct)) * 1000
        verdict = "meets" if overhead < 100 else "MISSES"
        print(f"  service overhead at p50: {overhead:.1f} ms ({verdict} the 100 ms target)")
        same_work = (statistics.median(phases["total"]) - statistics.median(direct_all)) * 1000
        print(f"  over the same work done directly (decode, register, write): {same_work:.1f} ms")

        if args.batch <= 0:
            return 0
        # Throughput, 1 worker against N workers (single-threaded workers, the default), and
        # the same jobs in a plain process pool calling the core (the machine's own ceiling:
        # no HTTP, no database, no client on the same cores). The four runs alternate, round
        # after round, so that a change of the machine's load shows in every ratio alike.
        n, w = args.batch, args.workers
        labels = {"s1": "service, 1 worker", "sN": f"service, {w} workers",
                  "c1": "core only, 1 process", "cN": f"core only, {w} processes"}
        runs: dict[str, list[dict[str, float]]] = {key: [] for key in labels}
        for r in range(args.rounds):
            for key, count in (("s1", 1), ("sN", w)):
                data = tmp_dir / f"batch-{r}-{key}" / "data"
                data.parent.mkdir()
                with service(count, data) as (url, pid):
                    runs[key].append(run_batch(url, pid, pair, n))
            for key, count in (("c1", 1), ("cN", w)):
                out = tmp_dir / f"core-{r}-{key}"
                out.mkdir()
                runs[key].append(core_batch(pair, n, count, out))

        def median(key: str, field: str) -> float:
            return statistics.median(run[field] for run in runs[key])

        print(f"\nthroughput, {n} jobs at once, median of {args.rounds} rounds")
        print(f"  {'':<26} {'wall s':>7} {'jobs/s':>7}   CPU ms per job: workers     api  "
              "client")
        for key, label in labels.items():
            cpu = "".join(f"{median(key, k) * 1000:8.1f}" if k in runs[key][0] else f"{'-':>8}"
                          for k in ("workers", "api", "client"))
            wall = median(key, "wall")
            print(f"  {label:<26} {wall:7.2f} {n / wall:7.2f}                  {cpu}")
        ratios = [a["wall"] / b["wall"] for a, b in zip(runs["s1"], runs["sN"], strict=True)]
        ceilings = [a["wall"] / b["wall"] for a, b in zip(runs["c1"], runs["cN"], strict=True)]
        ratio, ceiling = statistics.median(ratios), statistics.median(ceilings)
        verdict = "meets" if ratio >= 1.8 else "MISSES"
        print(f"throughput {w} workers / 1 worker: {ratio:.2f}x median ("
              + ", ".join(f"{x:.2f}" for x in ratios) + f"; {verdict} the 1.8x target)")
        print(f"the core alone, {w} processes / 1: {ceiling:.2f}x median ("
              + ", ".join(f"{x:.2f}" for x in ceilings) + f"); {os.cpu_count()} CPU cores")
        total = sum(median("sN", k) for k in ("workers", "api", "client")) * 1000
        print(f"  with {w} workers a job costs {total:.0f} CPU ms in all (workers "
              f"{median('sN', 'workers') * 1000:.0f}, API {median('sN', 'api') * 1000:.0f}, "
              f"client {median('sN', 'client') * 1000:.0f}): {os.cpu_count()} cores give at "
              f"most {os.cpu_count() / total * 1000:.2f} jobs/s")
    print("load average at end: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
