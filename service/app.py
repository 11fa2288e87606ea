"""Application factory: builds the FastAPI app and, in its lifespan, the store, the storage, the
queue with its worker processes and the maintenance thread."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from functools import partial
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from pwlreg.service import __version__
from pwlreg.service.api import jobs, ogc, system, viewer
from pwlreg.service.auth import load_api_keys
from pwlreg.service.deps import Services
from pwlreg.service.hrefs import HrefAllowList
from pwlreg.service.logs import job_extra
from pwlreg.service.maintenance import Janitor
from pwlreg.service.metrics import CountRefusals, Metrics
from pwlreg.service.problems import PROBLEM_MEDIA_TYPE, install_problem_handlers
from pwlreg.service.queue import CeleryQueue, JobQueue, LocalProcessQueue
from pwlreg.service.schemas import ExecuteRequest, Options
from pwlreg.service.settings import Settings
from pwlreg.service.storage import open_storage
from pwlreg.service.store import FINISHED, JobStore
from pwlreg.service.webhooks import Webhooks, load_secret
from pwlreg.service.worker import resolve_runner

log = logging.getLogger(__name__)

QueueFactory = Callable[[Settings, JobStore, Callable[[str], None]], JobQueue]
"""Builds the queue from the settings, the store and the callback of finished attempts."""

DESCRIPTION = """\
Piecewise-linear registration of an image pair: a Delaunay mesh over conjugate points, refined by
a mutual-information edge-swap optimizer. Submit a job with `POST /v1/jobs`, poll its status,
download its results. Resource names and status words follow OGC API - Processes; errors are
RFC 9457 problem documents (`application/problem+json`).

Pixel coordinates: x right, y down, (0, 0) the centre of the top-left pixel.
"""


def _default_queue(
    settings: Settings, store: JobStore, on_finished: Callable[[str], None]
) -> JobQueue:
    if settings.queue == "celery":
        return CeleryQueue(settings, store, on_finished)
    return LocalProcessQueue(settings, store, on_finished)


def create_app(settings: Settings | None = None, queue_factory: QueueFactory | None = None) -> (
    FastAPI
):
    """Build the application.

    Parameters
    ----------
    settings : Settings, optional
        Defaults to the settings read from the ``PWLREG_*`` environment.
    queue_factory : callable, optional
        Builds the job queue; defaults to the queue ``settings.queue`` names (a
        :class:`~service.queue.LocalProcessQueue` or a :class:`~service.queue.CeleryQueue`).

    Returns
    -------
    fastapi.FastAPI
        The app; the database, the queue and the workers start with its lifespan.
    """
    settings = settings or Settings()
    make_queue = queue_factory or _default_queue

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        resolve_runner(settings.runner)  # a misconfigured runner stops the start, loudly
        api_keys = load_api_keys(settings)  # so do malformed keys (the message shows no key)
        HrefAllowList.parse(settings.href_allow)  # and a malformed origin of PWLREG_HREF_ALLOW
        storage = open_storage(settings)
        storage.prepare()
        store = JobStore.from_url(settings.resolved_database_url)
        store.create_schema()
        metrics = Metrics()

        webhooks = Webhooks(settings, store, partial(jobs.webhook_body, storage=storage),
                            load_secret(settings))

        def on_finished(job_id: str) -> None:
            webhooks.wake()
            job = store.get(job_id)
            if job is not None and job.status in FINISHED and job.duration is not None:
                metrics.observe_job(job.status.value, job.duration, job.timings)
                log.info(
                    "job %s: %s after %.2f s", job_id, job.status.value, job.duration,
                    extra=job_extra(job_id, job.owner),
                )

        queue = make_queue(settings, store, on_finished)
        # Celery mode: the workers are processes of other services, not of this one.
        workers = settings.workers if settings.queue == "local" else 0
        metrics.track_store(store.count_by_status, queue.depth, workers)
        janitor = Janitor(settings, store, storage, queue)
        janitor.recover()  # jobs of a previous process that died go back to the queue
        queue.start()
        janitor.start()
        webhooks.start()  # also delivers what a previous process left pending
        app.state.services = Services(
            settings, store, storage, queue, metrics, api_keys, webhooks
        )
        log.info(
            "pwlreg ready: data in %s, %s, %s", settings.data_dir.resolve(),
            f"{workers} worker(s)" if workers else f"Celery queue {settings.broker_queue}",
            f"API keys of {len(api_keys)} client(s)" if api_keys else "no API keys (open access)",
        )
        try:
            yield
        finally:
            janitor.stop()
            queue.stop()
            webhooks.stop()
            store.dispose()

    app = FastAPI(
        title="pwlreg",
        version=__version__,
        summary="Piecewise-linear image registration as a service",
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # /docs and /redoc: the viewer router, from the package's own files
        redoc_url=None,
    )
    install_problem_handlers(app)
    app.add_middleware(CountRefusals)
    app.include_router(jobs.router)
    app.include_router(system.router)
    app.include_router(ogc.router)
    app.include_router(viewer.router)
    app.mount(viewer.STATIC_URL, viewer.static_files(), name="static")
    app.state.html_landing = viewer.index_page  # the HTML answer of / (ogc's landing page)
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app


def _openapi(app: FastAPI) -> dict[str, Any]:
    """The OpenAPI document, with problem answers as ``application/problem+json`` and the
    options model among the components (the multipart form refers to it)."""
    if app.openapi_schema:
        return app.openapi_schema
    doc = get_openapi(
        title=app.title,
        version=app.version,
        summary=app.summary,
        description=app.description,
        routes=app.routes,
        tags=[
            {"name": "jobs", "description": "Registration jobs and their results."},
            {"name": "system", "description": "Options, health, readiness and metrics."},
            {"name": "ogc", "description": "OGC API - Processes - Part 1: Core, over the same "
             "jobs."},
        ],
    )
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    options_schema = Options.model_json_schema(ref_template="#/components/schemas/{model}")
    schemas.update(options_schema.pop("$defs", {}))
    schemas["Options"] = options_schema
    execute_schema = ExecuteRequest.model_json_schema(ref_template="#/components/schemas/{model}")
    schemas.update(execute_schema.pop("$defs", {}))
    schemas["ExecuteRequest"] = execute_schema
    problem_ref = {"$ref": "#/components/schemas/ProblemDetails"}
    for path in doc.get("paths", {}).values():
        for operation in path.values():
            for code, response in operation.get("responses", {}).items():
                content = response.get("content", {})
                if code[0] not in "45" or not content:
                    continue
                # FastAPI files a problem model under the route's media type (text/plain for
                # /metrics): every error answer is a problem document.
                kind = "application/json" if "application/json" in content else next(iter(content))
                if kind != "application/json" and not content[kind].get("schema", {}).get(
                    "$ref", ""
                ).endswith("/ProblemDetails"):
                    continue
                media = content.pop(kind)
                if media.get("schema", {}).get("$ref", "").endswith("/HTTPValidationError"):
                    # FastAPI's own 422 answer: ours is a problem document.
                    media = {"schema": problem_ref}
                    response["description"] = "Invalid path, query or header parameter."
                content[PROBLEM_MEDIA_TYPE] = media
    for unused in ("HTTPValidationError", "ValidationError"):
        schemas.pop(unused, None)
    app.openapi_schema = doc
    return doc
