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
