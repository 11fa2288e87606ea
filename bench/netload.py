"""Load and fault scripts for the service on a shared network (issue 12).

``python -m bench.netload load``: 300 submissions from 30 concurrent clients with 3 API keys
against a ``pwlreg serve`` subprocess on 127.0.0.1 with small queue limits. Every request must
get ``201`` or ``429``; every accepted job must end ``successful``. It prints the answers by
status, the submit latency (p50/p95), and the server's memory (resident set of the server and
its workers) and open files sampled through the run, which must stay flat.

``python -m bench.netload fault``: a stream of 50 jobs during which a worker process is killed
(SIGKILL) at random moments and, separately, the whole server is killed and started again on
the same data directory. Afterwards every accepted job must be ``successful``, or ``failed``
with a reason; none lost, none stuck, none finished twice (each job's "successful" or "failed"
log line appears at most once).

Both only talk to 127.0.0.1, bound their loops in count and time, and stop by themselves.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
FINISHED = ("successful", "failed", "dismissed")


def make_pair(width: int = 320, height: int = 240, seed: int = 7) -> dict[str, bytes]:
    """A textured pair related by an affine map, with 40 grid points (files of one job)."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), 2.5)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    affine = np.array([[0.97, 0.04, 5.0], [-0.03, 1.02, -3.0]])
    moving = cv2.warpAffine(texture, affine, (width, height), borderMode=cv2.BORDER_REFLECT)
    xs, ys = np.meshgrid(np.linspace(24, width - 24, 8), np.linspace(24, height - 24, 5))
    ref = np.stack([xs.ravel(), ys.ravel()], axis=1)
    mov = ref @ affine[:, :2].T + affine[:, 2]
    return {
        "reference": cv2.imencode(".png", texture)[1].tobytes(),
        "moving": cv2.imencode(".png", moving)[1].tobytes(),
        "points": json.dumps({"reference": ref.tolist(), "moving": mov.tolist()}).encode(),
    }


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """A ``pwlreg serve`` subprocess on 127.0.0.1 (restartable on the same port and data)."""

    def __init__(self, data_dir: Path, env: dict[str, str]) -> None:
        self.data_dir, self.env = data_dir, env
        self.port = _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = data_dir.parent / "server.log"
        self.process: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 60.0) -> None:
        env = {**os.environ, **self.env, "PWLREG_DATA_DIR": str(self.data_dir),
               "PYTHONPATH": str(REPO)}
        with self.log_path.open("ab") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "pwlreg.service.cli", "serve", "--host", "127.0.0.1",
                 "--port", str(self.port), "--log-level", "info"],
                cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT,
            )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{self.url}/readyz", timeout=1.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"server not ready:\n{self.log_path.read_text()[-3000:]}")

    def pids(self) -> list[int]:
        assert self.process is not None
        out = subprocess.run(["pgrep", "-P", str(self.process.pid)], capture_output=True,
                             text=True, check=False)
        return [self.process.pid] + [int(p) for p in out.stdout.split()]

    def kill(self) -> None:
        assert self.process is not None
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(10)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()


def _rss_mb(pids: list[int]) -> float:
    total = 0
    for pid in pids:
        try:
            for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
        except OSError:
            pass
    return total / 1024


def _open_files(pids: list[int]) -> int:
    n = 0
    for pid in pids:
        try:
            n += len(os.listdir(f"/proc/{pid}/fd"))
        except OSError:
            pass
    return n


def _post(client: httpx.Client, files: dict[str, bytes], key: str | None) -> httpx.Response:
    headers = {"Authorization": f"Bearer {key}"} if key else {}
    parts = {name: (name, data) for name, data in files.items()}
    return client.post("/v1/jobs", files=parts, headers=headers)


def _wait_all(url: str, jobs: dict[str, str | None], timeout: float) -> dict[str, dict]:
    """Poll every job until it ends (or ``timeout`` runs out); returns the last documents."""
    docs: dict[str, dict] = {}
    deadline = time.monotonic() + timeout
    with httpx.Client(base_url=url, timeout=30.0) as client:
        pending = set(jobs)
        while pending and time.monotonic() < deadline:
            for job_id in list(pending):
                key = jobs[job_id]
                headers = {"Authorization": f"Bearer {key}"} if key else {}
                try:
                    r = client.get(f"/v1/jobs/{job_id}", headers=headers)
                except httpx.TransportError:
                    continue
                if r.status_code == 200:
                    docs[job_id] = r.json()
                    if docs[job_id]["status"] in FINISHED:
                        pending.discard(job_id)
            time.sleep(0.5)
    return docs


def load(args: argparse.Namespace) -> int:
    files = make_pair()
    keys = {"alpha": "key-alpha-1", "beta": "key-beta-2", "gamma": "key-gamma-3"}
    env = {
        "PWLREG_API_KEYS": ",".join(f"{n}:{k}" for n, k in keys.items()),
        "PWLREG_WORKERS": "2",
        "PWLREG_MAX_QUEUED_JOBS": str(args.max_queued),
        "PWLREG_MAX_QUEUED_PER_CLIENT": str(args.max_queued_per_client),
    }
    with tempfile.TemporaryDirectory() as tmp:
        server = Server(Path(tmp) / "data", env)
        server.start()
        samples: list[tuple[float, float, int]] = []
        done = threading.Event()

        def sample() -> None:
            t0 = time.monotonic()
            while not done.is_set() and time.monotonic() - t0 < 600:
                pids = server.pids()
                samples.append((time.monotonic() - t0, _rss_mb(pids), _open_files(pids)))
                done.wait(0.5)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        per_client = args.submissions // args.clients
        names = list(keys)
        answers: Counter[int] = Counter()
        latencies: list[float] = []
        accepted: dict[str, str | None] = {}
        lock = threading.Lock()

        def client_run(i: int) -> None:
            key = keys[names[i % len(names)]]
            with httpx.Client(base_url=server.url, timeout=60.0) as client:
                for _ in range(per_client):
                    t = time.perf_counter()
                    r = _post(client, files, key)
                    dt = time.perf_counter() - t
                    with lock:
                        answers[r.status_code] += 1
                        latencies.append(dt)
                        if r.status_code == 201:
                            accepted[r.json()["id"]] = key
                    if r.status_code == 429:
                        time.sleep(min(float(r.headers.get("Retry-After", "1")), 2.0) * 0.2)

        t0 = time.monotonic()
        with ThreadPoolExecutor(args.clients) as pool:
            list(pool.map(client_run, range(args.clients)))
        submit_s = time.monotonic() - t0
        docs = _wait_all(server.url, accepted, timeout=900)
        done.set()
        sampler.join()
        server.stop()
    statuses = Counter(d["status"] for d in docs.values())
    lat = np.array(latencies) * 1000
    print(f"submissions: {sum(answers.values())} from {args.clients} clients with "
          f"{len(keys)} keys in {submit_s:.1f} s; answers {dict(sorted(answers.items()))}")
    print(f"submit latency p50 {np.percentile(lat, 50):.1f} ms, p95 {np.percentile(lat, 95):.1f}"
          f" ms, max {lat.max():.1f} ms")
    print(f"accepted jobs {len(accepted)}: final statuses {dict(statuses)}, not finished "
          f"{len(accepted) - sum(statuses[s] for s in FINISHED)}")
    if samples:
        rss = [s[1] for s in samples]
        fds = [s[2] for s in samples]
        third = max(1, len(samples) // 3)
        print(f"server + workers memory MB: first {rss[0]:.0f}, max {max(rss):.0f}, "
              f"median of the last third {np.median(rss[-third:]):.0f}; open files: first "
              f"{fds[0]}, max {max(fds)}, last {fds[-1]}")
        marks = [samples[min(len(samples) - 1, int(q * (len(samples) - 1)))]
                 for q in (0.0, 0.25, 0.5, 0.75, 1.0)]
        print("  at 0/25/50/75/100 % of the run (s, MB, files): " + ", ".join(
            f"({t:.0f}, {m:.0f}, {f})" for t, m, f in marks))
    ok = set(answers) <= {201, 429} and statuses.get("successful", 0) == len(accepted)
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


def fault(args: argparse.Namespace) -> int:
    # Jobs long enough (automatic matching at 1024x768) for the kills to land in running
    # registrations.
    files = make_pair(1024, 768)
    del files["points"]
    env = {"PWLREG_WORKERS": "2", "PWLREG_LEASE_SECONDS": "3", "PWLREG_PROGRESS_INTERVAL": "0.2",
           "PWLREG_MAX_ATTEMPTS": "5"}
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        server = Server(Path(tmp) / "data", env)
        server.start()
        accepted: dict[str, str | None] = {}
        answers: Counter[int] = Counter()
        kills: Counter[str] = Counter()
        t0 = time.monotonic()
        with httpx.Client(base_url=server.url, timeout=60.0) as client:
            for i in range(args.jobs):
                for _attempt in range(20):
                    try:
                        r = _post(client, files, None)
                        break
                    except httpx.TransportError:
                        time.sleep(0.5)  # the server is being restarted
                else:
                    raise RuntimeError("the server did not come back")
                answers[r.status_code] += 1
                if r.status_code == 201:
                    accepted[r.json()["id"]] = None
                if i % 5 == 4:
                    time.sleep(rng.uniform(0.5, 2.5))
                    workers = server.pids()[1:]
                    if rng.random() < 0.7 and workers:
                        os.kill(rng.choice(workers), signal.SIGKILL)
                        kills["worker"] += 1
                    else:
                        server.kill()
                        kills["server"] += 1
                        server.start()
        docs = _wait_all(server.url, accepted, timeout=900)
        elapsed = time.monotonic() - t0
        server.stop()
        log = server.log_path.read_text(errors="replace")
    statuses = Counter(d["status"] for d in docs.values())
    ends = Counter(re.findall(r"job ([0-9a-f]{32}): (?:successful|failed)", log))
    twice = [j for j, n in ends.items() if n > 1]
    failed_without_reason = [
        j for j, d in docs.items()
        if d["status"] == "failed" and not (d.get("error") or {}).get("detail")
    ]
    lost = [j for j in accepted if j not in docs]
    stuck = [j for j, d in docs.items() if d["status"] not in FINISHED]
    print(f"answers {dict(answers)}; {len(accepted)} jobs accepted, {dict(kills)} kills, "
          f"{elapsed:.1f} s; final statuses "
          f"{dict(statuses)}; attempts {dict(Counter(d['attempts'] for d in docs.values()))}")
    print(f"lost {len(lost)}, stuck {len(stuck)}, failed without a reason "
          f"{len(failed_without_reason)}, finished twice {len(twice)}")
    for j, d in docs.items():
        if d["status"] == "failed":
            print(f"  failed {j}: {d['error']['detail'][:150]}")
    ok = (answers[201] == args.jobs and not lost and not stuck and not failed_without_reason
          and not twice)
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.netload", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("load", help="300 submissions from 30 clients with 3 keys")
    p.add_argument("--submissions", type=int, default=300)
    p.add_argument("--clients", type=int, default=30)
    p.add_argument("--max-queued", type=int, default=60)
    p.add_argument("--max-queued-per-client", type=int, default=25)
    p.set_defaults(run=load)
    f = sub.add_parser("fault", help="worker and server kills during 50 jobs")
    f.add_argument("--jobs", type=int, default=50)
    f.add_argument("--seed", type=int, default=1)
    f.set_defaults(run=fault)
    args = parser.parse_args(argv)
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
