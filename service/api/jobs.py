"""Jobs resource: submit, list, read, dismiss a registration job and download its results."""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import math
import re
import shutil
import threading
import uuid
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import urlencode

import numpy as np
from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from pydantic import ValidationError

from pwlreg.core.errors import InputError
from pwlreg.core.formats.geotiff import read_by_windows
from pwlreg.core.formats.points import is_gis_points
from pwlreg.core.io import load_json, load_points, probe_image
from pwlreg.core.matching import BORDER_TOLERANCE, MIN_MESH_PAIRS, inside_image
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.results import RESULTS, ResultFormat
from pwlreg.core.triangulation import delaunay_triangles
from pwlreg.service.auth import ClientDep
from pwlreg.service.deps import Services, ServicesDep
from pwlreg.service.logs import job_extra
from pwlreg.service.problems import (
    Problem,
    from_input_error,
    from_validation_error,
    idempotency_conflict,
    insufficient_storage,
    invalid_input,
    not_found,
    problem_responses,
    result_not_ready,
    too_many_jobs,
)
from pwlreg.service.schemas import JobList, Link, StatusInfo
from pwlreg.service.storage import IMAGES, Storage
from pwlreg.service.store import IdempotencyConflict, Job, JobStatus
from pwlreg.service.uploads import OVERHEAD_BYTES, ReceivedForm, receive_form
from pwlreg.service.webhooks import AllowList, parse_callback, webhook_info

log = logging.getLogger(__name__)

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

FORM_PARTS = ("reference", "moving", "points", "options")
WEBHOOK_PARTS = ("callback", "subscriber")
"""Small form fields (at most :data:`service.uploads.SMALL_PART_BYTES` each)."""
RESULTS_REL = "http://www.opengis.net/def/rel/ogc/1.0/results"
_KEY_PATTERN = re.compile(r"^[\x21-\x7e]{1,255}$")


# --- status documents ----------------------------------------------------------------------


def _root(request: Request) -> str:
    return request.scope.get("root_path", "").rstrip("/")


def job_href(request: Request, job_id: str) -> str:
    return f"{_root(request)}/v1/jobs/{job_id}"


def status_info(job: Job, request: Request) -> StatusInfo:
    """The status document of ``job``, with links relative to the server root."""
    return build_status(job, _root(request), request.app.state.services.storage)


def webhook_body(job: Job, storage: Storage) -> bytes:
    """The status document of ``job`` as a webhook sends it: the JSON of ``GET
    /v1/jobs/{id}``, with links absolute (the base URL the job was submitted to)."""
    base = (job.callback or {}).get("base_url") or ""
    return build_status(job, base, storage).model_dump_json().encode()


def build_status(job: Job, root: str, storage: Storage) -> StatusInfo:
    """The status document of ``job``, with links under ``root`` (a path prefix or a base
    URL), one per stored result."""
    href = f"{root}/v1/jobs/{job.id}"
    links = [Link(href=href, rel="self", type="application/json", title="This job")]
    if job.status == JobStatus.successful:
        for name in storage.result_names(job.id):
            result = RESULTS[name]
            links.append(
                Link(href=f"{href}/{result.route}", rel=RESULTS_REL, type=result.media_type,
                     title=result.title)
            )
    return StatusInfo(
        id=job.id,
        status=job.status,
        stage=job.stage if job.status == JobStatus.running else None,  # type: ignore[arg-type]
        progress=int(job.progress),
        message=job.message,
        attempts=job.attempts,
        created=job.created,
        started=job.started,
        finished=job.finished,
        updated=job.updated,
        options=job.options,
        has_points=job.has_points,
        quality=job.quality,
        links=links,
        error=job.error,  # type: ignore[arg-type]
        webhook=webhook_info(job),  # type: ignore[arg-type]
    )


def visible_job(services: Services, job_id: str, client: str | None) -> Job | None:
    """The job ``job_id`` if the client may see it: its own job, or any job without API keys
    (``client`` None); None otherwise, so that another client's job is answered exactly like a
    missing one."""
    job = services.store.get(job_id)
    if job is None or (client is not None and job.owner != client):
        return None
    return job


def _get_job(services: Services, job_id: str, client: str | None) -> Job:
    job = visible_job(services, job_id, client)
    if job is None:
        raise not_found(f"no job {job_id!r}")
    return job


# --- submission ----------------------------------------------------------------------------


def parse_options(data: bytes) -> dict[str, Any]:
    """The effective options (defaults included) of an ``options`` part, a JSON object."""
    text = data.decode("utf-8", "replace").strip()
    if not text:
        return RegistrationOptions().model_dump(mode="json")
    try:
        value = load_json(text, "options")
    except InputError as exc:
        raise from_input_error(exc) from None
    if not isinstance(value, dict):
        raise invalid_input("options must be a JSON object, e.g. {\"bins\": 32}", "options")
    try:
        return RegistrationOptions.model_validate(value).model_dump(mode="json")
    except ValidationError as exc:
        raise from_validation_error(exc, prefix="options") from None


def check_points(
    reference: np.ndarray, moving: np.ndarray, sizes: dict[str, tuple[int, int]]
) -> None:
    """Refuse, from the request alone, client points the registration could not use: fewer
    than :data:`core.matching.MIN_MESH_PAIRS` pairs, a point outside its image (beyond
    :data:`core.matching.BORDER_TOLERANCE` pixels; ``sizes`` are the images' ``(width,
    height)``), or all reference (or all moving) points collinear, so that no triangle can be
    built.

    Raises
    ------
    Problem
        422 with ``field`` ``points``.
    """
    if len(reference) < MIN_MESH_PAIRS:
        raise invalid_input(
            f"points: {len(reference)} pair(s) given, at least {MIN_MESH_PAIRS} are needed to "
            "build a mesh",
            "points",
        )
    for name, pts in (("reference", reference), ("moving", moving)):
        width, height = sizes[name]
        outside = np.flatnonzero(~inside_image(pts, (height, width), BORDER_TOLERANCE))
        if outside.size:
            i = int(outside[0])
            x, y = pts[i]
            raise invalid_input(
                f"points: {outside.size} {name} point(s) outside the {width}x{height} {name} "
                f"image, the first is pair {i} at ({x:g}, {y:g}); coordinates are pixels, x "
                f"right, y down, (0, 0) the centre of the top-left pixel, within "
                f"{BORDER_TOLERANCE:g} px of the border",
                "points",
            )
    for name, pts in (("reference", reference), ("moving", moving)):
        try:
            delaunay_triangles(pts)
        except InputError:
            raise invalid_input(
                f"points: the {name} points are all collinear (or coincide): no triangle can be "
                "built; give at least three points that span an area in both images",
                "points",
            ) from None


def validate_submission(form: ReceivedForm, max_pixels: int, max_raster_pixels: int
                        ) -> tuple[dict[str, Any], bool]:
    """Check every part of a submission without decoding the images.

    The images' kind, size (against ``max_pixels``, or ``max_raster_pixels`` for a TIFF read
    window by window, :func:`core.formats.geotiff.read_by_windows`) and structure are checked
    from their bytes (:func:`core.io.probe_image`); decoding them is left to the worker, so
    that the API process does little CPU work per upload and the worker pool is what scales.
    Client points are checked against the images' sizes (:func:`check_points`).

    Returns
    -------
    options : dict
        The effective options.
    has_points : bool
        True if conjugate points were sent.

    Raises
    ------
    Problem
        422 for a missing part, bad options or points and images over the pixel limit, 415 for
        a file that is not an image of a supported kind, or a truncated or damaged one.
    """
    for name in ("reference", "moving"):
        if name not in form.parts:
            raise invalid_input(f"the file part {name!r} is missing", name)
    options = (
        parse_options(form.parts["options"].path.read_bytes())
        if "options" in form.parts
        else RegistrationOptions().model_dump(mode="json")
    )
    has_points = "points" in form.parts
    try:
        sizes = {
            name: probe_image(form.parts[name].path, max_raster_pixels
                              if read_by_windows(form.parts[name].path) else max_pixels,
                              field=name)
            for name in IMAGES
        }
        points = None
        if has_points:
            data = form.parts["points"].path.read_bytes()
            points = load_points(data, field="points", reference=form.parts["reference"].path,
                                 moving=form.parts["moving"].path)
            if is_gis_points(data):  # the worker reads pixel pairs, placed once, here
                form.parts["points"].path.write_text(json.dumps(
                    {"reference": points[0].tolist(), "moving": points[1].tolist()}
                ))
    except InputError as exc:
        raise from_input_error(exc) from None
    if points is not None:
        check_points(points[0], points[1], sizes)
    return options, has_points


def _check_key(key: str | None) -> str | None:
    if key is None:
        return None
    if not _KEY_PATTERN.match(key):
        raise invalid_input(
            "Idempotency-Key must be 1 to 255 visible ASCII characters", "Idempotency-Key"
        )
    return key


def scoped_key(key: str | None, client: str | None) -> str | None:
    """The idempotency key as stored: the client's own key without API keys, else
    ``<client>/<SHA-256 of the key>``, so that two clients' keys never meet (and the stored
    key stays short)."""
    if key is None or client is None:
        return key
    return f"{client}/{hashlib.sha256(key.encode()).hexdigest()}"


def _retry_after(services: Services, queued: int) -> int:
    """Seconds a refused client should wait: about the time the workers need to take the jobs
    ahead of it, counted as one second per job and worker, between 1 and 60."""
    return max(1, min(60, math.ceil(queued / services.settings.workers)))


def check_queue(services: Services, client: str | None) -> None:
    """Refuse a new job (429 with ``Retry-After``) while too many jobs wait for a worker, in
    all or of this client (the per-client limit applies with API keys only)."""
    settings, store = services.settings, services.store
    queued = store.count_accepted()
    if queued >= settings.max_queued_jobs:
        log.warning("submission refused: %d jobs wait, the service limit is %d", queued,
                    settings.max_queued_jobs, extra={"client": client})
        raise too_many_jobs(
            f"{queued} jobs are waiting for a worker, the limit of the service is "
            f"{settings.max_queued_jobs}; try again later",
            _retry_after(services, queued),
        )
    if client is not None:
        mine = store.count_accepted(client)
        if mine >= settings.max_queued_per_client:
            log.warning("submission refused: %d jobs of the client wait, the limit is %d", mine,
                        settings.max_queued_per_client, extra={"client": client})
            raise too_many_jobs(
                f"{mine} of your jobs are waiting for a worker, the limit per client is "
                f"{settings.max_queued_per_client}; try again when some have started",
                _retry_after(services, queued),
            )


def check_disk(services: Services, content_length: str | None) -> None:
    """Refuse an upload (507) that would leave less than ``min_free_bytes`` free in the data
    directory (its declared length counted when known)."""
    settings = services.settings
    need = settings.min_free_bytes
    if need <= 0:
        return
    try:
        declared = max(0, int(content_length)) if content_length is not None else 0
    except ValueError:
        declared = 0  # refused as malformed by the receiver
    if declared <= len(FORM_PARTS) * settings.max_upload_bytes + OVERHEAD_BYTES:
        need += declared  # a longer body is refused with 413 by the receiver
    free = shutil.disk_usage(settings.data_dir).free
    if free < need:
        raise insufficient_storage(
            "the service has not enough free disk space for this upload; try again later"
        )


def _precheck(
    services: Services, client: str | None, key: str | None, content_length: str | None
) -> None:
    """The limits checked before the upload is received: a refused client sends nothing."""
    _check_queue_unless_replay(services, client, key)
    check_disk(services, content_length)


def _check_queue_unless_replay(services: Services, client: str | None, key: str | None) -> None:
    """:func:`check_queue` for a new job; a replay of a known idempotency ``key`` is answered
    whatever the queue. A full queue looks the key up again: the job that fills it may be the
    key's own, made by a request with the same key since the first lookup (twelve requests
    with one key at once on a full queue: one was refused)."""

    def replay() -> bool:
        return key is not None and services.store.get_by_idempotency_key(key) is not None

    if replay():
        return
    try:
        check_queue(services, client)
    except Problem:
        if not replay():
            raise


def _read_callback(
    form: ReceivedForm, allow: AllowList, base_url: str
) -> dict[str, Any] | None:
    """The webhook of a submission (form fields ``callback`` or ``subscriber``), checked."""
    texts = {
        name: form.parts[name].path.read_bytes().decode("utf-8", "replace")
        for name in WEBHOOK_PARTS
        if name in form.parts
    }
    urls = parse_callback(texts.get("callback"), texts.get("subscriber"), allow)
    return None if urls is None else {**urls, "base_url": base_url}


_ADMISSION = threading.Lock()
"""Held from the last queue check to the new job's row (:func:`_accept`)."""


def _accept(
    services: Services,
    form: ReceivedForm,
    staging: Path,
    key: str | None,
    client: str | None,
    base_url: str = "",
) -> tuple[Job, bool]:
    """Validate and store a submission; returns the job and whether it is new. ``key`` is the
    scoped idempotency key (:func:`scoped_key`); ``base_url`` makes the links of webhook
    deliveries absolute."""
    store, storage, settings = services.store, services.storage, services.settings
    fingerprint = form.fingerprint()
    if key is not None:
        existing = store.get_by_idempotency_key(key)
        if existing is not None:
            if existing.request_hash != fingerprint:
                raise idempotency_conflict(
                    f"the Idempotency-Key was used for job {existing.id} with another request",
                    existing.id,
                )
            return existing, False
    # Again: other jobs may have come while this one uploaded.
    _check_queue_unless_replay(services, client, key)
    options, has_points = validate_submission(form, settings.max_pixels,
                                              settings.max_raster_pixels)
    callback = _read_callback(form, AllowList.parse(settings.webhook_allow), base_url)
    job_id = uuid.uuid4().hex
    # Files first, then the row: a crash in between leaves files without a row (swept later),
    # never a row without its files.
    storage.commit_inputs(staging, job_id)
    try:
        # The last check and the row in one step: 30 submissions at once all passed the check
        # above while their images were validated, and 29 jobs waited under a limit of 5.
        with _ADMISSION:
            _check_queue_unless_replay(services, client, key)
            job, created = store.create(
                job_id,
                options,
                has_points,
                settings.max_attempts,
                idempotency_key=key,
                request_hash=fingerprint,
                owner=client,
                callback=callback,
            )
    except IdempotencyConflict as exc:
        storage.remove(job_id)
        raise idempotency_conflict(str(exc), exc.job.id) from None
    except BaseException:
        storage.remove(job_id)
        raise
    if not created:
        storage.remove(job_id)
    else:
        services.queue.enqueue(job.id)
    return job, created


_FORM_SCHEMA = {
    "type": "object",
    "required": ["reference", "moving"],
    "properties": {
        "reference": {
            "type": "string",
            "format": "binary",
            "description": "Reference image: PNG, JPEG, PPM/PGM or BMP (8 or 16 bit, grey or "
            "colour) or TIFF/GeoTIFF (1-N bands of 8/16/32-bit integers or 32/64-bit floats, "
            "nodata and masks honoured). A georeferenced reference adds registered.tif and "
            "GeoJSON in its CRS.",
        },
        "moving": {
            "type": "string",
            "format": "binary",
            "description": "Moving image (registered onto the reference), same formats.",
        },
        "points": {
            "type": "string",
            "description": "Optional conjugate points, as a file part or a form field: JSON "
            '{"reference": [[x, y], ...], "moving": [[x, y], ...]} or CSV with the header '
            "x,y,x_moving,y_moving (pixel coordinates, x right, y down, (0, 0) the centre of "
            "the top-left pixel); with a georeferenced reference also a QGIS Georeferencer "
            ".points file or a GeoTIFF carrying the moving image's GCPs (map coordinates, "
            "placed through the reference's geotransform). The format is sniffed. Without "
            "points, they are matched automatically.",
            "example": '{"reference": [[10, 12], [200, 15], [105, 180]], '
            '"moving": [[12, 11], [203, 17], [104, 184]]}',
        },
        "options": {
            "allOf": [{"$ref": "#/components/schemas/Options"}],
            "description": "Optional options as a JSON object, as a form field or a file part "
            "(see GET /v1/options). Unknown names are refused.",
        },
        "callback": {
            "type": "string",
            "format": "uri",
            "maxLength": 2048,
            "description": "Optional webhook: an http(s) URL to which the job's status document "
            "is POSTed, signed, when the job ends (successful, failed or dismissed). A URL whose "
            "host resolves to a loopback, link-local, private, multicast or unspecified address "
            "is refused (422) unless the service's allow-list permits it.",
            "example": "https://example.org/pwlreg-hook",
        },
        "subscriber": {
            "type": "string",
            "description": "Optional webhook, OGC API - Processes style (instead of callback): "
            'a JSON object {"successUri": ..., "failedUri": ...}; a successful job is announced '
            "to successUri, a failed or dismissed one to failedUri (inProgressUri is ignored).",
            "example": '{"successUri": "https://example.org/done", '
            '"failedUri": "https://example.org/failed"}',
        },
    },
}


@router.post(
    "",
    status_code=201,
    response_model=StatusInfo,
    summary="Submit a registration job",
    description="Upload a reference and a moving image (and optionally conjugate points and "
    "options) as multipart/form-data. The upload streams to disk; a part over the size limit "
    "is refused with 413. Answers 201 with the job's status document and its URL in "
    "`Location`. With an `Idempotency-Key` header, a repeated request returns the job of the "
    "first one (same answer) instead of creating a second job.",
    responses={
        201: {
            "description": "Job accepted (or the job of the same Idempotency-Key).",
            "headers": {
                "Location": {
                    "description": "URL of the job's status document.",
                    "schema": {"type": "string"},
                }
            },
        },
        **problem_responses(400, 401, 413, 415, 422, 429, 507),
    },
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "multipart/form-data": {
                    "schema": _FORM_SCHEMA,
                    "encoding": {
                        "options": {"contentType": "application/json"},
                        "subscriber": {"contentType": "application/json"},
                    },
                }
            },
        }
    },
)
async def submit_job(
    request: Request,
    response: Response,
    services: ServicesDep,
    client: ClientDep,
    idempotency_key: Annotated[
        str | None,
        Header(
            description="Client-chosen key (1-255 visible ASCII characters); the same key "
            "with the same request returns the same job.",
            examples=["a7c3e2d4-upload-42"],
        ),
    ] = None,
) -> StatusInfo:
    async def receive(staging: Path) -> ReceivedForm:
        return await receive_form(
            request.headers.get("content-type"),
            request.headers.get("content-length"),
            request.stream(),
            staging,
            FORM_PARTS + WEBHOOK_PARTS,
            services.settings.max_upload_bytes,
            small_parts=WEBHOOK_PARTS,
        )

    job, created = await submit(request, services, client, idempotency_key, receive)
    response.headers["Location"] = job_href(request, job.id)
    if not created:
        response.headers["Idempotent-Replayed"] = "true"
    return status_info(job, request)


async def submit(
    request: Request,
    services: Services,
    client: str | None,
    idempotency_key: str | None,
    receive: Callable[[Path], Awaitable[ReceivedForm]],
) -> tuple[Job, bool]:
    """Create a job from a request: the one way every API (``/v1``, OGC) submits a job.

    The limits that need no input are checked first (queue, disk space, the declared
    length), then ``receive(staging)`` stores the request's inputs as the parts of a form in
    the empty directory ``staging`` (``reference``, ``moving``, ``points``, ``options``,
    ``callback``, ``subscriber``), which are validated, moved to the job's storage, and the job
    row created and queued (:func:`_accept`). The staging directory is removed in every case.

    Returns
    -------
    job : Job
    created : bool
        False for the replay of a known ``Idempotency-Key``.

    Raises
    ------
    Problem
        As :func:`_accept`, ``receive``, and 507 when the disk is full.
    """
    key = scoped_key(_check_key(idempotency_key), client)
    await run_in_threadpool(_precheck, services, client, key,
                            request.headers.get("content-length"))
    storage = services.storage
    staging = await run_in_threadpool(storage.new_staging)
    try:
        form = await receive(staging)
        base_url = str(request.base_url).rstrip("/")
        job, created = await run_in_threadpool(
            _accept, services, form, staging, key, client, base_url
        )
    except OSError as exc:
        if exc.errno != errno.ENOSPC:
            raise
        raise insufficient_storage(
            "the service has no disk space left for this upload; try again later"
        ) from None
    finally:
        await run_in_threadpool(storage.discard, staging)
    if created:
        services.metrics.job_submitted(client)
        log.info("job %s: accepted", job.id, extra=job_extra(job.id, client))
    else:
        log.info("job %s: idempotent replay", job.id, extra=job_extra(job.id, client))
    return job, created


# --- reading, listing, dismissing ------------------------------------------------------------


@router.get(
    "",
    response_model=JobList,
    summary="List jobs",
    description="Jobs newest first, a page at a time, optionally only those with given "
    "statuses (repeat `status`).",
    responses=problem_responses(401, 422),
)
def list_jobs(
    request: Request,
    services: ServicesDep,
    client: ClientDep,
    status: Annotated[
        list[JobStatus] | None,
        Query(description="Only jobs with one of these statuses (repeatable).",
              examples=[["running"]]),
    ] = None,
    limit: Annotated[int, Query(ge=1, le=100, description="Jobs per page.")] = 20,
    offset: Annotated[
        int, Query(ge=0, le=2**53 - 1, description="Jobs to skip (newest first).")
    ] = 0,
) -> JobList:
    statuses = status or []
    jobs, matched = services.store.list(statuses, limit=limit, offset=offset, owner=client)
    base = f"{_root(request)}/v1/jobs"

    def page(at: int) -> str:
        query: list[tuple[str, Any]] = [("status", s.value) for s in statuses]
        query += [("limit", limit), ("offset", at)]
        return f"{base}?{urlencode(query)}"

    links = [Link(href=page(offset), rel="self", type="application/json", title="This page")]
    if offset + len(jobs) < matched:
        links.append(
            Link(href=page(offset + limit), rel="next", type="application/json",
                 title="Next page")
        )
    if offset > 0:
        links.append(
            Link(href=page(max(0, offset - limit)), rel="prev", type="application/json",
                 title="Previous page")
        )
    return JobList(
        jobs=[status_info(j, request) for j in jobs],
        numberMatched=matched,
        numberReturned=len(jobs),
        links=links,
    )


@router.get(
    "/{job_id}",
    response_model=StatusInfo,
    summary="Status of a job",
    description="Status, stage and progress of a job; once successful, links to every result. "
    "A failed job carries the reason as a problem document in `error`.",
    responses=problem_responses(401, 404),
)
def get_job(
    job_id: str, request: Request, services: ServicesDep, client: ClientDep
) -> StatusInfo:
    return status_info(_get_job(services, job_id, client), request)


@router.delete(
    "/{job_id}",
    status_code=204,
    response_class=Response,
    summary="Dismiss a job",
    description="Cancel a queued or running job (the worker stops at its next progress check) "
    "and remove its files, inputs and results. The job stays listed as dismissed until the "
    "retention removes it. Dismissing a dismissed job does nothing.",
    responses={204: {"description": "Dismissed."}, **problem_responses(401, 404)},
)
def dismiss_job(job_id: str, services: ServicesDep, client: ClientDep) -> Response:
    dismiss(services, _get_job(services, job_id, client))
    return Response(status_code=204)


def dismiss(services: Services, job: Job) -> None:
    """Dismiss ``job`` (every API does it this way): mark it dismissed, so that its worker
    stops, remove its files and let the webhook loop announce it."""
    services.store.dismiss(job.id)
    services.storage.remove(job.id)
    log.info("job %s: dismissed by the client", job.id, extra=job_extra(job.id, job.owner))
    if services.webhooks is not None:
        services.webhooks.wake()


# --- results -------------------------------------------------------------------------------


def _result(services: Services, job_id: str, key: str, client: str | None) -> FileResponse:
    job = _get_job(services, job_id, client)
    if job.status != JobStatus.successful:
        raise result_not_ready(job.id, job.status.value)
    path = services.storage.result_path(job_id, key)
    result = RESULTS[key]
    if path is None:
        raise not_found(f"job {job_id} has no {result.filename} result (not produced for this "
                        "job, or no longer stored)")
    return FileResponse(
        path,
        media_type=result.media_type,
        filename=result.filename,
        content_disposition_type="inline",
    )


def _add_result_route(fmt: ResultFormat) -> None:
    def get_result(job_id: str, services: ServicesDep, client: ClientDep) -> FileResponse:
        return _result(services, job_id, fmt.name, client)

    for method in ("GET", "HEAD"):
        router.add_api_route(
            f"/{{job_id}}/{fmt.route}",
            get_result,
            methods=[method],
            response_class=FileResponse,
            operation_id=f"{method.lower()}_{fmt.name}",
            summary=fmt.title if method == "GET" else f"{fmt.title} (headers only)",
            description=fmt.description,
            responses={200: {"content": {fmt.media_type: {}}, "description": fmt.filename},
                       **problem_responses(401, 404, 409)},
        )


for _fmt in RESULTS.values():
    _add_result_route(_fmt)
