"""One process at a time compiles the kernels into numba's on-disk cache.

numba's cache takes no lock between processes. Processes that compile the same kernels at the
same time can leave object code in it that crashes (a segmentation fault) every later process
that loads it (numba issues 4807 and 10128; seen here with the service's workers warming up
beside a registration on a cold cache, after which every search in every new process crashed
until the cache was deleted). :func:`prepare` lets the first process that finds the cache
without this source's marker compile everything while it holds an exclusive lock on a file
beside the cache; the others wait for the lock, find the marker and load what it compiled.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import logging
import sys
from collections.abc import Callable
from pathlib import Path

import numba
from llvmlite import binding as llvm

from pwlreg.core import kernels, tiled

try:
    import fcntl
except ImportError:  # not POSIX: no lock (the race stays possible there)
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

LOCK_NAME = "pwlreg-kernels.lock"


def cache_directory() -> Path | None:
    """Where numba keeps the compiled kernels of :mod:`pwlreg.core.kernels` (its own choice:
    ``NUMBA_CACHE_DIR``, the package's ``__pycache__`` or the user's cache); None when it
    caches nothing (``NUMBA_DISABLE_JIT``, caching off)."""
    path = getattr(getattr(kernels.search_run, "_cache", None), "_cache_path", None)
    return Path(path) if path else None


@functools.cache
def cache_key(compile_all: Callable[[], None] | None = None) -> str:
    """What the cached kernels depend on: their sources, the types ``compile_all`` compiles
    them for (its code), numba, Python and the CPU."""
    digest = hashlib.sha256()
    for module in (kernels, tiled):
        digest.update(Path(module.__file__).read_bytes())
    if compile_all is not None:
        try:
            digest.update(inspect.getsource(compile_all).encode())
        except (OSError, TypeError):  # no source (defined in ``python -c``): its name
            digest.update(getattr(compile_all, "__qualname__", "").encode())
    cpu = numba.core.config.CPU_NAME or llvm.get_host_cpu_name()
    digest.update(f"{numba.__version__}|{sys.version_info[:2]}|{cpu}".encode())
    return digest.hexdigest()[:16]


def prepare(compile_all: Callable[[], None], *, load: bool = False,
            directory: Path | None = None) -> bool:
    """Have the on-disk cache hold the kernels, compiled by one process at a time.

    Parameters
    ----------
    compile_all : callable
        Compiles (or loads) every kernel: runs each with every type it is called with.
    load : bool
        Run ``compile_all`` even when the cache is ready, to have the kernels in this process
        before their first use (a service worker before its first job).
    directory : Path, optional
        The cache directory (default :func:`cache_directory`).

    Returns
    -------
    bool
        Whether ``compile_all`` ran in this call.
    """
    directory = directory if directory is not None else cache_directory()
    if directory is None or fcntl is None:
        if load:
            compile_all()
        return load
    marker = directory / f"pwlreg-kernels-{cache_key(compile_all)}.ready"
    if marker.exists():
        if load:
            compile_all()
        return load
    try:
        directory.mkdir(parents=True, exist_ok=True)
        handle = open(directory / LOCK_NAME, "a+b")  # noqa: SIM115 (held across the compile)
    except OSError as exc:
        log.warning("cannot lock numba's cache in %s (%s); compiling without the lock",
                    directory, exc)
        compile_all()
        return True
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            ready = marker.exists()
            if not ready:
                log.info("compiling the kernels into %s (once; minutes)", directory)
                compile_all()
                marker.touch()
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
    if ready and load:
        compile_all()
    return not ready or load
