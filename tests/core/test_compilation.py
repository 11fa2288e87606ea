"""One process at a time compiles the kernels into numba's cache."""

from __future__ import annotations

import multiprocessing
import time
from pathlib import Path

from pwlreg.core import compilation


def _compile_slowly(log: Path) -> None:
    with log.open("a") as f:
        f.write(f"start {time.monotonic()}\n")
    time.sleep(0.5)
    with log.open("a") as f:
        f.write(f"end {time.monotonic()}\n")


def _prepare(directory: str, log: str, load: bool, results: multiprocessing.Queue) -> None:
    results.put(compilation.prepare(lambda: _compile_slowly(Path(log)), load=load,
                                    directory=Path(directory)))


def test_concurrent_processes_compile_once_and_never_at_the_same_time(tmp_path: Path) -> None:
    log = tmp_path / "log"
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    # Two processes that find a cold cache, and a worker that loads the kernels in any case.
    processes = [context.Process(target=_prepare, args=(str(tmp_path), str(log), load, results))
                 for load in (False, False, True)]
    for process in processes:
        process.start()
    for process in processes:
        process.join(60)
        assert process.exitcode == 0
    ran = [results.get(timeout=5) for _ in processes]
    events = [line.split() for line in log.read_text().splitlines()]
    spans = list(zip(events[::2], events[1::2], strict=True))
    # One compiled; the worker loaded too unless it was the one that compiled.
    assert sum(ran) == len(spans) in (1, 2)
    assert all(start[0] == "start" and end[0] == "end" for start, end in spans)
    # Never two at once: the loading began after the compilation (under the lock) ended.
    assert all(float(a[1][1]) <= float(b[0][1]) for a, b in zip(spans, spans[1:], strict=False))
    assert list(tmp_path.glob("pwlreg-kernels-*.ready"))


def test_a_ready_cache_is_not_compiled_again(tmp_path: Path) -> None:
    calls: list[int] = []

    def compile_all() -> None:
        calls.append(1)

    assert compilation.prepare(compile_all, directory=tmp_path) is True
    assert compilation.prepare(compile_all, directory=tmp_path) is False
    assert compilation.prepare(compile_all, load=True, directory=tmp_path) is True
    assert calls == [1, 1]


def test_another_warm_up_is_compiled_again(tmp_path: Path) -> None:
    # The marker follows the warm-up's code: one that compiles more types (an 8-bit image
    # against a 16-bit one) does not find the cache ready.
    def first() -> None:
        pass

    def second() -> None:
        pass

    assert compilation.prepare(first, directory=tmp_path) is True
    assert compilation.prepare(second, directory=tmp_path) is True
    assert compilation.prepare(second, directory=tmp_path) is False


def test_a_failed_compilation_leaves_the_cache_not_ready(tmp_path: Path) -> None:
    def fail() -> None:
        raise RuntimeError("killed")

    try:
        compilation.prepare(fail, directory=tmp_path)
    except RuntimeError:
        pass
    assert not list(tmp_path.glob("pwlreg-kernels-*.ready"))
    calls: list[int] = []
    assert compilation.prepare(lambda: calls.append(1), directory=tmp_path) is True
    assert calls == [1]


def test_the_kernels_cache_is_found_where_numba_keeps_it() -> None:
    directory = compilation.cache_directory()
    assert directory is not None
    assert len(compilation.cache_key()) == 16
