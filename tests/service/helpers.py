"""Helpers of the service tests: a synthetic pair, a real server process, client calls."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
from prometheus_client.parser import text_string_to_metric_families

REPO = Path(__file__).resolve().parents[2]
FINISHED = ("successful", "failed", "dismissed")
PROBLEM_TYPE = "application/problem+json"


# --- synthetic pair ------------------------------------------------------------------------


@dataclass(frozen=True)
class Pair:
    """A textured reference, the moving image made by a known affine warp, and grid points
    mapped through the same affine (x right, y down, pixel centres)."""

    reference_png: bytes
    moving_png: bytes
    points_json: bytes
    affine: np.ndarray  # 2x3, moving = A @ [x, y, 1]
    reference_points: np.ndarray
    moving_points: np.ndarray

    def points_csv(self) -> bytes:
        rows = ["x,y,x_moving,y_moving"] + [
            f"{a[0]:.4f},{a[1]:.4f},{b[0]:.4f},{b[1]:.4f}"
            for a, b in zip(self.reference_points, self.moving_points, strict=True)
        ]
        return ("\n".join(rows) + "\n").encode()


def make_pair(width: int = 320, height: int = 240, seed: int = 7) -> Pair:
    rng = np.random.default_rng(seed)
    noise = rng.random((height, width)).astype(np.float32)
    texture = cv2.GaussianBlur(noise, (0, 0), 2.5)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    affine = np.array([[0.97, 0.04, 5.0], [-0.03, 1.02, -3.0]])
    moving = cv2.warpAffine(texture, affine, (width, height), borderMode=cv2.BORDER_REFLECT)
    xs, ys = np.meshgrid(np.linspace(24, width - 24, 8), np.linspace(24, height - 24, 5))
    ref_pts = np.stack([xs.ravel(), ys.ravel()], axis=1)
    mov_pts = ref_pts @ affine[:, :2].T + affine[:, 2]
    doc = {"reference": ref_pts.tolist(), "moving": mov_pts.tolist()}
    return Pair(
        reference_png=cv2.imencode(".png", texture)[1].tobytes(),
        moving_png=cv2.imencode(".png", moving)[1].tobytes(),
        points_json=json.dumps(doc).encode(),
        affine=affine,
        reference_points=ref_pts,
        moving_points=mov_pts,
    )


# --- server processes ------------------------------------------------------------------------


def png_file(width: int, height: int, idat: bytes) -> bytes:
    """A structurally valid 8-bit grey PNG (every chunk's CRC right) announcing ``width x
    height`` pixels, with ``idat`` as its compressed pixel data, whatever that holds."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return b"".join((len(data).to_bytes(4, "big"), kind, data,
                         zlib.crc32(kind + data).to_bytes(4, "big")))

    ihdr = b"".join((width.to_bytes(4, "big"), height.to_bytes(4, "big"), bytes((8, 0, 0, 0, 0))))
    return b"".join((b"\x89PNG\r\n\x1a\n", chunk(b"IHDR", ihdr), chunk(b"IDAT", idat),
                     chunk(b"IEND", b"")))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """A ``pwlreg serve`` subprocess.

    Parameters
    ----------
    data_dir : Path
        Its data directory (kept across restarts).
    env : dict
        ``PWLREG_*`` settings.
    log_level : str
        ``--log-level`` of ``pwlreg serve``.
    """

    def __init__(self, data_dir: Path, env: dict[str, str], log_level: str = "warning") -> None:
        self.data_dir = data_dir
        self.env = env
        self.log_level = log_level
        self.process: subprocess.Popen[bytes] | None = None
        self.port = 0
        self.log_path = data_dir.parent / f"{data_dir.name}-server.log"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout: float = 60.0) -> Server:
        self.port = free_port()
        env = {**os.environ, **self.env, "PWLREG_DATA_DIR": str(self.data_dir)}
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
        log = self.log_path.open("ab")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "pwlreg.service.cli", "serve", "--host", "127.0.0.1",
             "--port", str(self.port), "--log-level", self.log_level],
            cwd=REPO,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        log.close()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise AssertionError(f"server exited with {self.process.returncode}:\n{self.log()}")
            try:
                if httpx.get(f"{self.url}/readyz", timeout=1.0).status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise AssertionError(f"server not ready after {timeout} s:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")[-5000:] if self.log_path.exists() else ""

    def children(self) -> list[int]:
        """Pids of the server's child processes (workers, resource tracker)."""
        assert self.process is not None
        out = subprocess.run(["pgrep", "-P", str(self.process.pid)], capture_output=True,
                             text=True, check=False)
        return [int(p) for p in out.stdout.split()]

    def kill(self) -> None:
        """SIGKILL the server process (its workers follow it)."""
        assert self.process is not None
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(10)

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM (graceful shutdown), SIGKILL if it does not exit."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(10)
            raise AssertionError(f"server ignored SIGTERM:\n{self.log()}") from None

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=30.0)


BASE_ENV = {
    "PWLREG_WORKERS": "2",
    "PWLREG_LEASE_SECONDS": "3",
    "PWLREG_PROGRESS_INTERVAL": "0.1",
    "PWLREG_MAX_UPLOAD_BYTES": str(400 * 1024),
    "PWLREG_MAX_PIXELS": str(500_000),
    "PWLREG_MAX_ATTEMPTS": "3",
}


# --- client helpers ------------------------------------------------------------------------


def submit(
    client: httpx.Client,
    pair: Pair,
    points: bytes | None | str = "json",
    options: dict[str, Any] | None = None,
    headers: dict[str, str] | None = None,
) -> httpx.Response:
    """POST a job with the pair (and the points as a JSON file part unless told otherwise)."""
    files: dict[str, Any] = {
        "reference": ("reference.png", pair.reference_png, "image/png"),
        "moving": ("moving.png", pair.moving_png, "image/png"),
    }
    if points == "json":
        files["points"] = ("points.json", pair.points_json, "application/json")
    elif isinstance(points, bytes):
        files["points"] = ("points", points, "application/octet-stream")
    data = {"options": json.dumps(options)} if options is not None else None
    return client.post("/v1/jobs", files=files, data=data, headers=headers or {})


def wait_for(
    client: httpx.Client,
    job_id: str,
    until: Callable[[dict[str, Any]], bool] = lambda job: job["status"] in FINISHED,
    timeout: float = 30.0,
    interval: float = 0.05,
) -> dict[str, Any]:
    """Poll a job until ``until(job)``; fail clearly with the last document on timeout."""
    deadline = time.monotonic() + timeout
    job: dict[str, Any] = {}
    while time.monotonic() < deadline:
        response = client.get(f"/v1/jobs/{job_id}")
        assert response.status_code == 200, response.text
        job = response.json()
        if until(job):
            return job
        time.sleep(interval)
    raise AssertionError(f"job {job_id} did not reach the condition in {timeout} s: {job}")


def assert_problem(response: httpx.Response, status: int, field: str | None = None) -> dict:
    """Check an RFC 9457 problem answer and return its document."""
    assert response.status_code == status, (response.status_code, response.text)
    assert response.headers["content-type"].startswith(PROBLEM_TYPE), response.headers
    doc = response.json()
    assert doc["status"] == status
    assert doc["type"].startswith("urn:pwlreg:problem:")
    assert isinstance(doc["title"], str) and doc["title"]
    assert isinstance(doc["detail"], str) and doc["detail"]
    if field is not None:
        assert doc.get("field") == field, doc
    return doc


# --- metrics ---------------------------------------------------------------------------------


Samples = dict[str, list[tuple[dict[str, str], float]]]


def metric_samples(text: str) -> Samples:
    """The samples of a Prometheus exposition text, by sample name (``x_total``,
    ``x_bucket``, ...), each as (labels, value); the text must parse."""
    samples: Samples = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            samples.setdefault(sample.name, []).append((dict(sample.labels), sample.value))
    return samples


def one(samples: Samples, name: str, **labels: str) -> float:
    """The value of the one sample ``name`` with exactly ``labels`` (0 if there is none)."""
    values = [value for got, value in samples.get(name, []) if got == labels]
    assert len(values) <= 1, (name, labels, values)
    return values[0] if values else 0.0
