"""Session set-up shared by every test."""

from __future__ import annotations

import pytest

from pwlreg.core.pipeline import warm_up


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels() -> None:
    """Compile the kernels into numba's cache (on a cold cache, once, under the cache's lock)
    before any test starts a server, whose workers load them: a test that compiled a kernel
    while a worker compiled it too could leave a cache that crashes later processes."""
    warm_up(load=False)
