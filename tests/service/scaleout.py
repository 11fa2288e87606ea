"""Fixtures and helpers of the scale-out tests: real PostgreSQL and Redis, ``pwlreg worker``
processes.

PostgreSQL and Redis are the machine's (127.0.0.1:5432, user postgres, and 127.0.0.1:6379, or
``PWLREG_TEST_POSTGRES`` / ``PWLREG_TEST_REDIS``). A server that does not answer is started with
the machine's command when it is installed; otherwise the tests that need it are skipped, naming
what is missing. Each test gets its own new database (dropped afterwards) and its own Redis
database number and queue name, so that runs side by side do not meet.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import psycopg
import pytest
import redis

from tests.service.helpers import REPO

POSTGRES = os.environ.get("PWLREG_TEST_POSTGRES", "postgresql://postgres@127.0.0.1:5432/postgres")
REDIS = os.environ.get("PWLREG_TEST_REDIS", "redis://127.0.0.1:6379")

START = {
    "PostgreSQL": (
        "pg_ctlcluster",
        "pg_ctlcluster --skip-systemctl-redirect $(ls /etc/postgresql) main start",
    ),
    "Redis": (
        "redis-server",
        "redis-server --daemonize yes --bind 127.0.0.1 -::1 --port 6379 --save '' "
        "--appendonly no --dir /var/lib/redis --logfile /var/log/redis/ci.log",
    ),
}


def _answers(url: str) -> bool:
    parts = urlsplit(url)
    try:
        with socket.create_connection((parts.hostname, parts.port), timeout=1.0):
            return True
    except OSError:
        return False


def ensure_running(name: str, url: str) -> None:
    """Skip the test unless the server ``name`` at ``url`` answers, after starting it with the
    machine's command if it does not."""
    if _answers(url):
        return
    executable, command = START[name]
    if shutil.which(executable) is None:
        pytest.skip(f"{name} does not answer at {url} and is not installed ({executable})")
    subprocess.run(command, shell=True, capture_output=True, timeout=60, check=False)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        if _answers(url):
            return
        time.sleep(0.2)
    pytest.skip(f"{name} does not answer at {url}, and `{command}` did not start it")


@pytest.fixture()
def database() -> Iterator[str]:
    """The SQLAlchemy URL of a new, empty PostgreSQL database, dropped after the test."""
    ensure_running("PostgreSQL", POSTGRES)
    name = f"pwlreg_test_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(POSTGRES, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    parts = urlsplit(POSTGRES)
    yield parts._replace(scheme="postgresql+psycopg", path=f"/{name}").geturl()
    with psycopg.connect(POSTGRES, autocommit=True) as admin:
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


@pytest.fixture()
def broker() -> Iterator[dict[str, str]]:
    """The settings of a Redis broker for one test: a database number and a queue name of its
    own. The queue's keys are deleted after the test."""
    ensure_running("Redis", REDIS)
    number = random.randint(1, 15)
    queue = f"pwlreg-test-{uuid.uuid4().hex[:12]}"
    url = f"{REDIS.rstrip('/')}/{number}"
    yield {"PWLREG_QUEUE": "celery", "PWLREG_BROKER_URL": url, "PWLREG_BROKER_QUEUE": queue}
    client = redis.Redis.from_url(url)
    forget(client, queue)
    client.close()


def forget(client: redis.Redis, queue: str) -> None:
    """Delete the keys of ``queue`` and its messages left unacknowledged by killed workers
    (kombu keeps those, of every queue of the database, in ``unacked``)."""
    keys = list(client.scan_iter(match=f"*{queue}*"))
    if keys:
        client.delete(*keys)
    for tag, payload in client.hgetall("unacked").items():
        if queue in payload.decode(errors="replace"):
            client.hdel("unacked", tag)
            client.zrem("unacked_index", tag)


class Worker:
    """A ``pwlreg worker`` subprocess in a process group of its own (the Celery main process
    and its pool processes), like one container of the compose file.

    Parameters
    ----------
    data_dir : Path
        The data directory it shares with the API.
    env : dict
        ``PWLREG_*`` settings.
    name : str
        Names its log file, next to the data directory.
    """

    def __init__(self, data_dir: Path, env: dict[str, str], name: str) -> None:
        self.data_dir = data_dir
        self.env = env
        self.log_path = data_dir.parent / f"{data_dir.name}-{name}.log"
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> Worker:
        env = {**os.environ, **self.env, "PWLREG_DATA_DIR": str(self.data_dir)}
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
        with self.log_path.open("ab") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "pwlreg.service.cli", "worker", "--concurrency", "1",
                 "--log-level", "info"],
                cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        return self

    def wait_ready(self, timeout: float = 60.0) -> Worker:
        """Wait for Celery's 'ready' line."""
        assert self.process is not None
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise AssertionError(f"worker exited with {self.process.returncode}:\n{self.log()}")
            if " ready." in self.log():
                return self
            time.sleep(0.1)
        raise AssertionError(f"worker not ready after {timeout} s:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def pids(self) -> set[int]:
        """The worker's processes: its main process and the pool processes."""
        assert self.process is not None
        out = subprocess.run(["pgrep", "-g", str(self.process.pid)], capture_output=True,
                             text=True, check=False)
        return {int(p) for p in out.stdout.split()}

    def signal(self, signum: int) -> None:
        """Send ``signum`` to every process of the worker."""
        assert self.process is not None
        os.killpg(self.process.pid, signum)

    def kill(self) -> None:
        """SIGKILL the whole worker (main and pool processes at once), as a machine dies."""
        assert self.process is not None
        os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait(10)

    def terminate(self) -> None:
        """SIGTERM: a warm shutdown begins."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM (warm shutdown), SIGKILL of the group if it does not end."""
        if self.process is None:
            return
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()
        try:
            os.killpg(self.process.pid, signal.SIGKILL)  # pool processes left behind, if any
        except ProcessLookupError:
            pass
