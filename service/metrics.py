"""Prometheus metrics of one application instance, with ``prometheus_client``.

Each application owns a :class:`~prometheus_client.CollectorRegistry` (not the library's global
one), so that several applications in one process do not share or clash over their metrics.

* Gauges read from the store at scrape time (:class:`StoreCollector`): jobs by status, queue
  depth, workers.
* Counters observed in the API process: jobs submitted and submissions refused, per client.
* Histograms observed in the API process when it learns that an attempt ended, from the job row:
  the job duration by final status and, for a successful job, the seconds of each stage (the
  registration's timings, which the worker stores in the row). Counters and histograms restart
  at zero with the process, as Prometheus expects.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Histogram
from prometheus_client.exposition import generate_latest
from prometheus_client.metrics_core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from pwlreg.service.store import JobStatus

DURATION_BUCKETS: tuple[float, ...] = (0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600, 1800)
"""Upper bounds of the job duration histogram, in seconds (``+Inf`` is implicit)."""

STAGE_BUCKETS: tuple[float, ...] = (
    0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600, 1800
)
"""Upper bounds of the stage duration histogram, in seconds."""

CONTENT_TYPE = CONTENT_TYPE_LATEST
"""Media type of the exposition text."""

NO_CLIENT = ""
"""The ``client`` label when no client is known: open access, or a request refused before its
API key was recognised (401)."""


class StoreCollector(Collector):
    """Gauges read when Prometheus scrapes: jobs by status, queue depth, workers.

    Parameters
    ----------
    counts : callable
        Number of jobs per status (:meth:`service.store.JobStore.count_by_status`).
    depth : callable
        Jobs waiting for a worker (:meth:`service.queue.JobQueue.depth`).
    workers : int
        Worker processes of the service.
    """

    def __init__(
        self, counts: Callable[[], Mapping[JobStatus, int]], depth: Callable[[], int], workers: int
    ) -> None:
        self.counts = counts
        self.depth = depth
        self.workers = workers

    def _families(self, read: bool) -> Iterable[Metric]:
        jobs = GaugeMetricFamily("pwlreg_jobs", "Jobs in the store, by status.", labels=["status"])
        if read:
            counts = self.counts()
            for status in JobStatus:
                jobs.add_metric([status.value], counts.get(status, 0))
        yield jobs
        yield GaugeMetricFamily(
            "pwlreg_queue_depth", "Accepted jobs waiting for a worker.",
            value=self.depth() if read else None,
        )
        yield GaugeMetricFamily(
            "pwlreg_workers", "Worker processes of this service.",
            value=self.workers if read else None,
        )

    def describe(self) -> Iterable[Metric]:
        return list(self._families(read=False))

    def collect(self) -> Iterable[Metric]:
        return list(self._families(read=True))


class Metrics:
    """The metrics of one application instance, in its own registry."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.jobs_submitted = Counter(
            "pwlreg_jobs_submitted", "Jobs created by POST /v1/jobs (not idempotent replays), "
            "by client.", ["client"], registry=self.registry,
        )
        self.submissions_refused = Counter(
            "pwlreg_submissions_refused", "POST /v1/jobs answered with an error, by client and "
            "HTTP status code.", ["client", "code"], registry=self.registry,
        )
        self.job_duration = Histogram(
            "pwlreg_job_duration_seconds", "Duration of finished job attempts (start to end), "
            "by final status.", ["status"], buckets=DURATION_BUCKETS, registry=self.registry,
        )
        self.stage_duration = Histogram(
            "pwlreg_stage_duration_seconds", "Seconds each stage of a successful job took, by "
            "stage.", ["stage"], buckets=STAGE_BUCKETS, registry=self.registry,
        )

    def track_store(
        self, counts: Callable[[], Mapping[JobStatus, int]], depth: Callable[[], int],
        workers: int,
    ) -> None:
        """Add the gauges read at scrape time (:class:`StoreCollector`)."""
        self.registry.register(StoreCollector(counts, depth, workers))

    def job_submitted(self, client: str | None) -> None:
        self.jobs_submitted.labels(client=client or NO_CLIENT).inc()

    def submission_refused(self, client: str | None, code: int) -> None:
        self.submissions_refused.labels(client=client or NO_CLIENT, code=str(code)).inc()

    def observe_job(
        self, status: str, seconds: float, stages: Mapping[str, float] | None = None
    ) -> None:
        """Record a finished job: its duration (start of the attempt to its end, seconds) and
        the seconds of its stages, if known."""
        self.job_duration.labels(status=status).observe(max(0.0, seconds))
        for stage, stage_seconds in (stages or {}).items():
            self.stage_duration.labels(stage=stage).observe(max(0.0, float(stage_seconds)))

    def render(self) -> bytes:
        """The exposition text (:data:`CONTENT_TYPE`)."""
        return generate_latest(self.registry)


SUBMISSION_PATHS = ("/v1/jobs", "/processes/pwl-registration/execution")
"""The paths of the two ways to submit a job (the ``/v1`` API and OGC API - Processes)."""


class CountRefusals:
    """ASGI middleware counting the answers of a submission (:data:`SUBMISSION_PATHS`) that
    refuse it (status 400 and above), by client (``request.state.client``, set by
    :func:`service.auth.get_client`) and status code, in the metrics of the application."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] != "http"
            or scope["method"] != "POST"
            or not scope["path"].rstrip("/").endswith(SUBMISSION_PATHS)
        ):
            await self.app(scope, receive, send)
            return
        state: dict[str, Any] = scope.setdefault("state", {})
        status = 0  # no answer (e.g. the client went away): not counted

        async def send_and_note(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_and_note)
        finally:
            services = getattr(scope["app"].state, "services", None)
            if status >= 400 and services is not None:
                services.metrics.submission_refused(state.get("client"), status)
