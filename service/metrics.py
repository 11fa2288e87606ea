"""Prometheus metrics in the text exposition format (version 0.0.4), without a client library.

Gauges (jobs by status, queue depth, workers) are read from the store at scrape time; the job
duration histogram is observed in this process when an attempt ends, and restarts at zero with
the process, as Prometheus counters do.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Mapping, Sequence

from service.store import JobStatus

DURATION_BUCKETS: tuple[float, ...] = (0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600, 1800)
"""Upper bounds of the job duration histogram, in seconds (``+Inf`` is implicit)."""

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


class Histogram:
    """A cumulative histogram with labels, for the Prometheus text format."""

    def __init__(self, buckets: Sequence[float]) -> None:
        self.buckets = tuple(sorted(buckets))
        self._counts: dict[str, list[int]] = {}
        self._sums: dict[str, float] = {}
        self._lock = threading.Lock()

    def observe(self, label: str, value: float) -> None:
        """Add one observation ``value`` under ``label``."""
        with self._lock:
            counts = self._counts.setdefault(label, [0] * (len(self.buckets) + 1))
            counts[bisect.bisect_left(self.buckets, value)] += 1
            self._sums[label] = self._sums.get(label, 0.0) + value

    def render(self, name: str, label_name: str) -> list[str]:
        with self._lock:
            items = sorted((k, list(v), self._sums[k]) for k, v in self._counts.items())
        lines = []
        for label, counts, total in items:
            cumulative = 0
            for bound, n in zip((*self.buckets, math.inf), counts, strict=True):
                cumulative += n
                le = "+Inf" if math.isinf(bound) else _number(bound)
                lines.append(f'{name}_bucket{{{label_name}="{label}",le="{le}"}} {cumulative}')
            lines.append(f'{name}_sum{{{label_name}="{label}"}} {_number(total)}')
            lines.append(f'{name}_count{{{label_name}="{label}"}} {cumulative}')
        return lines


def _number(x: float) -> str:
    return repr(float(x))


class Metrics:
    """The metrics of one service process."""

    def __init__(self) -> None:
        self.job_duration = Histogram(DURATION_BUCKETS)

    def observe_job(self, status: str, seconds: float) -> None:
        """Record the duration (start of the attempt to its end, seconds) of a finished job."""
        self.job_duration.observe(status, max(0.0, seconds))

    def render(
        self, jobs_by_status: Mapping[JobStatus, int], queue_depth: int, workers: int
    ) -> str:
        """The exposition text."""
        lines = [
            "# HELP pwlreg_jobs Jobs in the store, by status.",
            "# TYPE pwlreg_jobs gauge",
        ]
        for status in JobStatus:
            lines.append(f'pwlreg_jobs{{status="{status.value}"}} {jobs_by_status.get(status, 0)}')
        lines += [
            "# HELP pwlreg_queue_depth Accepted jobs waiting for a worker.",
            "# TYPE pwlreg_queue_depth gauge",
            f"pwlreg_queue_depth {queue_depth}",
            "# HELP pwlreg_workers Worker processes of this service.",
            "# TYPE pwlreg_workers gauge",
            f"pwlreg_workers {workers}",
            "# HELP pwlreg_job_duration_seconds Duration of finished job attempts (start to end), "
            "by final status.",
            "# TYPE pwlreg_job_duration_seconds histogram",
        ]
        lines += self.job_duration.render("pwlreg_job_duration_seconds", "status")
        return "\n".join(lines) + "\n"
