"""Fixtures of the service tests: real uvicorn processes on 127.0.0.1 and a synthetic pair.

Every server runs ``python -m pwlreg.service.cli serve`` in a subprocess on a free port, with its
own data directory (SQLite database and files) under pytest's tmp dir, and worker processes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from tests.service.helpers import BASE_ENV, Pair, Server, make_pair


@pytest.fixture(scope="session")
def pair() -> Pair:
    return make_pair()


@pytest.fixture(scope="session")
def start_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Callable[..., Server]]:
    """Start servers (stopped at the end of the session): ``start_server(**env)``; the data
    directory can be given to restart over the same data, and the log level (default
    ``warning``)."""
    servers: list[Server] = []

    def start(data_dir: Path | None = None, log_level: str = "warning", **env: str) -> Server:
        data_dir = data_dir or tmp_path_factory.mktemp("service") / "data"
        server = Server(data_dir, {**BASE_ENV, **env}, log_level).start()
        servers.append(server)
        return server

    yield start
    for server in servers:
        server.stop()


@pytest.fixture(scope="session")
def server(start_server: Callable[..., Server]) -> Server:
    """The shared server: real ``core.pipeline.register``, 2 workers, small limits."""
    return start_server()


@pytest.fixture(scope="session")
def slow_server(start_server: Callable[..., Server]) -> Server:
    """One worker whose registration first spends 30 s in 'matching' (progress every 50 ms),
    then runs the real registration: jobs that stay running long enough to be cancelled."""
    return start_server(
        PWLREG_WORKERS="1",
        PWLREG_RUNNER="tests.service.runners:slow_register",
        PWLREG_TEST_SLOW_SECONDS="30",
    )


