"""Registration functions injected into test servers through ``PWLREG_RUNNER``."""

from __future__ import annotations

import os
import time
from typing import Any

from pwlreg.core.pipeline import register


def slow_register(reference: Any, moving: Any, points: Any = None, options: Any = None,
                  progress: Any = None) -> Any:
    """Spend ``PWLREG_TEST_SLOW_SECONDS`` in 'matching', reporting progress every 50 ms (so a
    job stays running long enough to be cancelled or killed), then register for real."""
    seconds = float(os.environ.get("PWLREG_TEST_SLOW_SECONDS", "5"))
    steps = max(1, int(seconds / 0.05))
    for i in range(steps):
        if progress is not None:
            progress("matching", 0.5 * i / steps)
        time.sleep(0.05)
    return register(reference, moving, points=points, options=options, progress=progress)


def crash_register(reference: Any, moving: Any, points: Any = None, options: Any = None,
                   progress: Any = None) -> Any:
    """Kill the worker process (as a crash inside a native library does) when the job's
    options carry ``seed`` 13; otherwise :func:`slow_register`."""
    seed = options.get("seed") if isinstance(options, dict) else getattr(options, "seed", None)
    if seed == 13:
        time.sleep(0.5)  # the other job is running by then
        os._exit(139)
    return slow_register(reference, moving, points, options, progress)
