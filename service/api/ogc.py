"""OGC API - Processes - Part 1: Core (OGC 18-062r2) over the job store of ``/v1``.

One process, ``pwl-registration``, executed synchronously or asynchronously: ``POST
/processes/pwl-registration/execution`` creates a job through the same function as ``POST
/v1/jobs`` (:func:`service.api.jobs.submit`), with the same checks, limits, API keys and owner
isolation. With ``Prefer: respond-async`` the answer is the job (201); without, the request
waits for the job, at most :data:`SYNC_WAIT_S` seconds (or the client's ``Prefer: wait``), and
answers its results (200), or the job when it takes longer: the job is queued and runs
whatever the answer, so nothing accepted is lost. ``/jobs`` shows the same jobs as
``/v1/jobs``. The results document links the result files of ``/v1/jobs/{id}/...``, declared
once in :data:`core.results.RESULTS`.

The landing page ``/`` is negotiated: JSON for ``?f=json`` or an ``Accept`` header preferring
``application/json`` (and for clients that do not ask for HTML), otherwise the HTML page of the
application's hook ``app.state.html_landing`` (a callable ``(request) -> Response``, set by the
viewer), or a redirect to ``/docs`` while there is none.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import functools
import hashlib
import inspect
import json
import logging
import math
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import urlencode

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, RedirectResponse
from pydantic import ValidationError
from python_multipart.multipart import parse_options_header

from pwlreg.core.errors import InputError
from pwlreg.core.io import load_json
from pwlreg.core.results import RESULTS
from pwlreg.service import __version__
from pwlreg.service.api import jobs
from pwlreg.service.api.system import describe_options
from pwlreg.service.auth import ClientDep, bearer, get_client
from pwlreg.service.deps import Services, ServicesDep, get_services
from pwlreg.service.hrefs import FetchError, HrefAllowList, TooLarge, fetch_href
from pwlreg.service.logs import job_extra
from pwlreg.service.problems import (
    TYPE_PREFIX,
    Problem,
    from_validation_error,
    invalid_input,
    malformed_request,
    problem_responses,
    result_not_ready,
    unsupported_media,
    upload_too_large,
)
from pwlreg.service.schemas import (
    ConformanceDeclaration,
    ExecuteRequest,
    LandingPage,
    OgcJobList,
    OgcLink,
    OgcStatusInfo,
    ParameterDescription,
    ProblemDetails,
    ProcessDescription,
    ProcessList,
    ProcessSummary,
    Results,
)
from pwlreg.service.store import FINISHED, Job, JobStatus, utcnow
from pwlreg.service.uploads import OVERHEAD_BYTES, Part, ReceivedForm
from pwlreg.service.webhooks import TargetError

router = APIRouter(tags=["ogc"])
log = logging.getLogger(__name__)

PROCESS_ID = "pwl-registration"
REL = "http://www.opengis.net/def/rel/ogc/1.0/"
EXCEPTIONS = "http://www.opengis.net/def/exceptions/ogcapi-processes-1/1.0/"
CONFORMANCE = [
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/core",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/ogc-process-description",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/json",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/dismiss",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/job-list",
]
"""Classes implemented in full (``/openapi.json`` is OpenAPI 3.1, not the oas30 class)."""

JSON = "application/json"

SYNC_WAIT_S = 20
"""Longest time (seconds) a synchronous execution waits for its job before answering it
asynchronously: shorter than the time outs of common HTTP clients and proxies (30-60 s), long
enough for a registration of a few megapixels."""

IMAGES = ("reference", "moving")
INPUTS = (*IMAGES, "points", "options")
IMAGE_MEDIA_TYPES = (
    "image/png", "image/jpeg", "image/tiff", "image/x-portable-anymap", "image/bmp",
)
"""Media types described for the images; the kind is read from the bytes (any ``image/*``
type is accepted)."""

_OGC_404 = {
    "model": ProblemDetails,
    "description": "No such process or job, or no results yet: `type` is the exception URI of "
    "the standard (`.../no-such-process`, `.../no-such-job`, `.../result-not-ready`).",
}


class OgcProblem(Problem):
    """A problem whose ``type`` is an exception URI of the standard (``no-such-job``, ...)."""

    def to_dict(self) -> dict[str, Any]:
        return {**super().to_dict(), "type": EXCEPTIONS + self.slug}


def _root(request: Request) -> str:
    return request.scope.get("root_path", "").rstrip("/")


def _link(request: Request, path: str, rel: str, title: str, type: str = JSON) -> OgcLink:
    return OgcLink(href=f"{_root(request)}{path}", rel=rel, type=type, title=title)


# --- landing page, conformance ----------------------------------------------------------------


def _wants_json(request: Request, f: str | None) -> bool:
    """JSON unless HTML is asked for (``f=html``, or ``text/html`` in ``Accept`` with a
    quality at least that of ``application/json``)."""
    if f is not None:
        return f == "json"
    quality: dict[str, float] = {}
    for item in request.headers.get("accept", "").split(","):
        media, params = parse_options_header(item)
        try:
            q = float(params.get(b"q", b"1"))
        except ValueError:
            q = 0.0
        kind = media.decode("latin-1").lower()
        quality[kind] = max(q, quality.get(kind, 0.0))
    html = quality.get("text/html", 0.0)
    return html == 0.0 or quality.get(JSON, 0.0) > html


def redirect_to_docs(request: Request) -> Response:
    """The HTML landing page until the viewer sets ``app.state.html_landing``."""
    return RedirectResponse(f"{_root(request)}/docs", status_code=303)


@router.get(
    "/",
    response_model=LandingPage,
    response_model_exclude_none=True,
    summary="Landing page",
    description="JSON (`?f=json`, or `Accept: application/json`): links to the API definition, "
    "the conformance declaration, the processes and the jobs. A browser (`Accept: text/html`, "
    "or `?f=html`) gets the HTML page.",
    responses={200: {"content": {"text/html": {}}},
               303: {"description": "HTML asked for: the interactive API documentation."},
               **problem_responses(401, 422)},
    openapi_extra={"security": [{"apiKey": []}, {}]},
)
async def landing_page(
    request: Request,
    response: Response,
    f: Annotated[
        Literal["json", "html"] | None, Query(description="Format, instead of `Accept`.")
    ] = None,
) -> Any:
    if not _wants_json(request, f):
        page = getattr(request.app.state, "html_landing", redirect_to_docs)
        answer = page(request)
        answer = await answer if inspect.isawaitable(answer) else answer
        answer.headers.setdefault("Vary", "Accept")
        return answer
    # API keys apply to the JSON document only (a browser's page carries no data), so the
    # caller is identified here rather than by a dependency of the route.
    get_client(request, get_services(request), await bearer(request))
    response.headers["Vary"] = "Accept"
    return LandingPage(
        title="pwlreg",
        description="Piecewise-linear registration of an image pair (OGC API - Processes).",
        links=[
            _link(request, "/?f=json", "self", "This document"),
            _link(request, "/openapi.json", "service-desc", "The API definition (OpenAPI 3.1)",
                  "application/vnd.oai.openapi+json;version=3.1"),
            _link(request, "/docs", "service-doc", "The API documentation", "text/html"),
            _link(request, "/conformance", f"{REL}conformance", "Conformance classes"),
            _link(request, "/processes", f"{REL}processes", "The processes"),
            _link(request, "/jobs", f"{REL}job-list", "The jobs"),
        ],
    )


@router.get(
    "/conformance",
    response_model=ConformanceDeclaration,
    summary="Conformance classes",
    description="The classes of OGC API - Processes - Part 1 the service implements.",
    responses=problem_responses(401),
)
def conformance(client: ClientDep) -> ConformanceDeclaration:
    return ConformanceDeclaration(conformsTo=CONFORMANCE)


# --- the process ----------------------------------------------------------------------------


def _options_schema() -> dict[str, Any]:
    """The options as an OpenAPI 3.0 schema object, from the options model."""
    properties = {}
    for option in describe_options():
        prop: dict[str, Any] = {"type": option.type, "default": option.default,
                                "description": option.help}
        if option.choices is not None:
            prop["enum"] = option.choices
        for bound in ("minimum", "maximum"):
            if getattr(option, bound) is not None:
                prop[bound] = getattr(option, bound)
            exclusive = getattr(option, f"exclusive_{bound}")
            if exclusive is not None:  # OpenAPI 3.0 writes an exclusive bound as a flag
                prop[bound] = exclusive
                prop[f"exclusive{bound.capitalize()}"] = True
        properties[option.name] = prop
    return {"type": "object", "additionalProperties": False, "properties": properties}


_PAIRS = {"type": "array", "minItems": 3, "items": {
    "type": "array", "minItems": 2, "maxItems": 2, "items": {"type": "number"}}}


@functools.cache
def process_description() -> dict[str, Any]:
    """The description of ``pwl-registration`` (links relative to the root, added per
    request); its outputs are :data:`core.results.RESULTS`."""
    image = {"oneOf": [{"type": "string", "contentEncoding": "binary", "contentMediaType": mt}
                       for mt in IMAGE_MEDIA_TYPES]}
    inputs = {
        "reference": ParameterDescription(
            title="Reference image",
            description="The image the moving image is registered onto: PNG, JPEG, TIFF, "
            "PPM/PGM or BMP, 8 or 16 bit, grey or colour. Base64 in a qualified value, or a "
            "link to an origin the service reads from.",
            minOccurs=1, maxOccurs=1, value_schema=image,
        ),
        "moving": ParameterDescription(
            title="Moving image",
            description="The image registered onto the reference, same formats.",
            minOccurs=1, maxOccurs=1, value_schema=image,
        ),
        "points": ParameterDescription(
            title="Conjugate points",
            description="Optional pairs of points: reference[i] in the reference image "
            "matches moving[i] in the moving image, pixel coordinates (x right, y down, (0, 0) "
            "the centre of the top-left pixel), at least 3 pairs. A JSON object, or the CSV "
            "text x,y,x_moving,y_moving. Without points, they are matched automatically.",
            minOccurs=0, maxOccurs=1,
            value_schema={"oneOf": [
                {"type": "object", "required": ["reference", "moving"],
                 "properties": {"reference": _PAIRS, "moving": _PAIRS},
                 "contentMediaType": JSON},
                {"type": "string", "contentMediaType": "text/csv"},
            ]},
        ),
        "options": ParameterDescription(
            title="Options",
            description="Optional options of the registration (GET /v1/options); unknown "
            "names are refused, missing ones take their default.",
            minOccurs=0, maxOccurs=1, value_schema=_options_schema(),
        ),
    }
    outputs = {
        fmt.name: ParameterDescription(
            title=fmt.title,
            description=fmt.description,
            value_schema={"type": "object", "contentMediaType": fmt.media_type}
            if fmt.media_type == JSON or fmt.media_type.endswith("+json")
            else {"type": "string", "contentEncoding": "binary",
                  "contentMediaType": fmt.media_type},
        )
        for fmt in RESULTS.values()
    }
    return ProcessDescription(
        id=PROCESS_ID,
        version=__version__,
        title="Piecewise-linear registration of an image pair",
        description="A Delaunay mesh over conjugate points (given or matched automatically), "
        "refined by edge swaps that maximize the mutual information of the images triangle by "
        "triangle; the moving image is then resampled onto the reference.",
        keywords=["image registration", "piecewise linear", "mutual information",
                  "co-registration"],
        jobControlOptions=["sync-execute", "async-execute", "dismiss"],
        outputTransmission=["reference"],
        inputs=inputs,
        outputs=outputs,
        links=[],
    ).model_dump(by_alias=True, exclude_none=True)


def _process_links(request: Request) -> list[OgcLink]:
    return [
        _link(request, f"/processes/{PROCESS_ID}", "self", "Process description"),
        _link(request, f"/processes/{PROCESS_ID}/execution", f"{REL}execute",
              "Execute the process"),
    ]


def _check_process(process_id: str) -> None:
    if process_id != PROCESS_ID:
        raise OgcProblem(404, "no-such-process", "No such process",
                         f"no process {process_id!r}; the process of this service is "
                         f"{PROCESS_ID!r}")


@router.get(
    "/processes",
    response_model=ProcessList,
    response_model_exclude_none=True,
    summary="Processes",
    description="The processes of the service: pwl-registration.",
    responses=problem_responses(401, 422),
)
def list_processes(
    request: Request,
    client: ClientDep,
    limit: Annotated[
        int, Query(ge=1, le=10000, description="Processes per page (there is one process).")
    ] = 10,
) -> ProcessList:
    summary = {k: v for k, v in process_description().items() if k not in ("inputs", "outputs")}
    return ProcessList(
        processes=[ProcessSummary.model_validate({**summary, "links": _process_links(request)})],
        links=[_link(request, "/processes", "self", "This document")],
    )


@router.get(
    "/processes/{processId}",
    response_model=ProcessDescription,
    response_model_exclude_none=True,
    summary="Process description",
    description="Inputs and outputs of the process with the schemas of their values.",
    responses={404: _OGC_404, **problem_responses(401)},
)
def describe_process(
    request: Request,
    client: ClientDep,
    process_id: Annotated[str, PathParam(alias="processId")],
) -> ProcessDescription:
    _check_process(process_id)
    return ProcessDescription.model_validate(
        {**process_description(), "links": _process_links(request)}
    )


# --- execution --------------------------------------------------------------------------------


def _body_limit(max_upload: int) -> int:
    """Largest execute request: both images inline in base64, points and options."""
    return 2 * 4 * math.ceil(max_upload / 3) + 2 * max_upload + OVERHEAD_BYTES


async def _read_body(request: Request, limit: int) -> bytes:
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise upload_too_large(f"the execute request is larger than {limit} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


def _store(staging: Path, name: str, data: bytes) -> Part:
    path = staging / name
    path.write_bytes(data)
    return Part(name, path, None, len(data), hashlib.sha256(data).hexdigest())


def _b64(field: str, value: str) -> bytes:
    try:
        return base64.b64decode("".join(value.split()), validate=True)
    except (binascii.Error, ValueError):
        raise invalid_input(f"{field}: the value is not valid base64", field) from None


def _inline(name: str, value: Any) -> bytes:
    """The bytes of the inline value of input ``name``, bare or qualified (``{"value": ...,
    "mediaType": ..., "encoding": ...}``): an image's base64 decoded, a string's text (its
    base64 decoded with ``"encoding": "base64"``), an object as JSON."""
    field = f"inputs.{name}"
    media_type, encoding = None, None
    if isinstance(value, dict) and "value" in value:
        extra = set(value) - {"value", "mediaType", "encoding", "schema"}
        if extra:
            raise invalid_input(f"{field}: unknown member(s) {sorted(extra)} of a qualified "
                                "value", field)
        media_type, encoding, value = value.get("mediaType"), value.get("encoding"), value["value"]
        if media_type is not None and not isinstance(media_type, str):
            raise invalid_input(f"{field}.mediaType must be a string", field)
        if encoding not in (None, "base64"):
            raise invalid_input(f"{field}: encoding {encoding!r} is not supported; binary "
                                "values are base64", field)
    if name in IMAGES:
        if media_type is not None and not media_type.lower().startswith("image/"):
            raise unsupported_media(f"{field}: mediaType {media_type!r} is not an image type",
                                    field)
        if not isinstance(value, str):
            raise invalid_input(f"{field}: an image is given as a base64 string (or a link)",
                                field)
        return _b64(field, value)
    if isinstance(value, str):
        return _b64(field, value) if encoding == "base64" else value.encode()
    if name == "options" and not isinstance(value, dict):
        raise invalid_input(f"{field} must be an object, e.g. {{\"bins\": 32}}", field)
    if name == "points" and not isinstance(value, dict):
        raise invalid_input(f"{field} must be an object {{\"reference\": [[x, y], ...], "
                            "\"moving\": [[x, y], ...]}, or CSV text", field)
    return json.dumps(value).encode()


async def _receive_execute(request: Request, services: Services, staging: Path) -> ReceivedForm:
    """Store the inputs of an execute request in ``staging`` as the parts of a /v1 form:
    inline values decoded, links read (:func:`service.hrefs.fetch_href`)."""
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media != JSON:
        raise unsupported_media("an execute request is a JSON document (Content-Type: "
                                "application/json)")
    settings = services.settings
    body = await _read_body(request, _body_limit(settings.max_upload_bytes))
    try:
        document = await run_in_threadpool(load_json, body, "the execute request")
    except InputError as exc:
        raise malformed_request(str(exc)) from None
    try:
        execute = ExecuteRequest.model_validate(document)
    except ValidationError as exc:
        raise from_validation_error(exc) from None
    for output, selection in (execute.outputs or {}).items():
        if output not in RESULTS:
            raise invalid_input(f"outputs: no output {output!r}; the outputs are "
                                + ", ".join(RESULTS), f"outputs.{output}")
        if selection.transmissionMode == "value":
            raise invalid_input("outputs are transmitted by reference only",
                                f"outputs.{output}.transmissionMode")
    if execute.response == "raw":
        raise invalid_input("only response=document is supported", "response")
    unknown = set(execute.inputs) - set(INPUTS)
    if unknown:
        name = sorted(unknown)[0]
        raise invalid_input(f"inputs: no input {name!r}; the inputs are " + ", ".join(INPUTS),
                            f"inputs.{name}")
    for name in IMAGES:
        if name not in execute.inputs:
            raise invalid_input(f"the input {name!r} is required", f"inputs.{name}")
    form = ReceivedForm()
    limit = settings.max_upload_bytes
    allow = HrefAllowList.parse(settings.href_allow)
    for name, value in execute.inputs.items():
        field = f"inputs.{name}"
        if isinstance(value, list):
            raise invalid_input(f"{field} takes one value, not an array", field)
        if isinstance(value, dict) and "href" in value:
            path = staging / name
            try:
                size, digest = await fetch_href(str(value["href"]), allow, path,
                                                max_bytes=limit, timeout=settings.href_timeout)
            except TargetError as exc:
                raise invalid_input(f"{field}: {exc}", field) from None
            except TooLarge as exc:
                raise upload_too_large(f"{field}: {exc}; the limit is {limit} bytes",
                                       field) from None
            except FetchError as exc:
                raise invalid_input(f"{field}: {exc}", field) from None
            form.parts[name] = Part(name, path, None, size, digest)
            continue
        data = await run_in_threadpool(_inline, name, value)
        if len(data) > limit:
            raise upload_too_large(f"{field} is larger than the limit of {limit} bytes", field)
        form.parts[name] = await run_in_threadpool(_store, staging, name, data)
    if execute.subscriber is not None:
        text = execute.subscriber.model_dump_json(exclude_none=True)
        form.parts["subscriber"] = await run_in_threadpool(_store, staging, "subscriber",
                                                           text.encode())
    return form


def _as_input(problem: Problem) -> Problem:
    """``problem`` with the form part it names (``reference``, ``options.bins``, ...) named as
    the input of the execute request (``inputs.reference``, ``inputs.options.bins``)."""

    def rename(field: str | None) -> str | None:
        if field is not None and field.split(".")[0] in INPUTS:
            return f"inputs.{field}"
        return field

    problem.field = rename(problem.field)
    if isinstance(problem.extra.get("errors"), list):
        problem.extra["errors"] = [{**e, "field": rename(e.get("field"))}
                                   for e in problem.extra["errors"]]
    return problem


def preferences(headers: list[str]) -> dict[str, str | None]:
    """The preferences of ``Prefer`` headers (RFC 7240): token (lower case) -> value (None
    without one); parameters are ignored and the first of a repeated token counts."""
    found: dict[str, str | None] = {}
    for header in headers:
        for item in header.split(","):
            token, _, value = item.split(";")[0].partition("=")
            token = token.strip().lower()
            if token:
                found.setdefault(token, value.strip().strip('"') or None)
    return found


def _sync_wait(prefer: dict[str, str | None]) -> tuple[float, list[str]]:
    """How long a synchronous execution waits, seconds, and the ``wait`` preference applied
    (none when the client gave none, or none that is a number of seconds)."""
    value = prefer.get("wait")
    if value is None or not (value.isascii() and value.isdigit()):
        return SYNC_WAIT_S, []
    wait = min(int(value), SYNC_WAIT_S)
    return wait, [f"wait={wait}"]


async def _finished(request: Request, services: Services, job: Job, wait: float) -> Job | None:
    """``job`` once finished, or None if it is not within ``wait`` seconds or the client hung
    up (the job runs on either way)."""
    deadline = time.monotonic() + wait
    pause = 0.05
    while True:
        current = await run_in_threadpool(services.store.get, job.id)
        if current is None or current.status in FINISHED:
            return current
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        if await request.is_disconnected():
            log.info("job %s: the client stopped waiting; the job runs on", job.id,
                     extra=job_extra(job.id, job.owner))
            return None
        # Quick jobs answer quickly; long ones cost the database a read every half second.
        await asyncio.sleep(min(pause, left))
        pause = min(2 * pause, 0.5)


_MONITOR = {"description": "`</jobs/{jobId}>; rel=\"monitor\"`: the job that ran.",
            "schema": {"type": "string"}}


@router.post(
    "/processes/{processId}/execution",
    status_code=201,
    response_model=OgcStatusInfo,
    response_model_exclude_none=True,
    summary="Execute the process",
    description="Create a job from an execute request (JSON). With `Prefer: respond-async` "
    "the answer is 201 with the job's status and its URL in `Location`. Without it the "
    f"request waits for the job, at most {SYNC_WAIT_S} s (less with `Prefer: wait=<seconds>`): "
    "200 with the results document (and the job in a `Link` header, `rel=monitor`) when it "
    "succeeds, its error when it fails, and when it takes longer the 201 answer of an "
    "asynchronous execution with `Preference-Applied: respond-async`; the job runs to its end "
    "whatever the answer. Inputs are inline (images in base64 in a qualified value with "
    "their `mediaType`, points and options as JSON) or links (`href`) to origins the service "
    "reads from (PWLREG_HREF_ALLOW). Every check of `POST /v1/jobs` applies; errors name the "
    "input (`inputs.<id>`).",
    responses={
        200: {"model": Results, "description": "Executed synchronously: the results.",
              "headers": {"Link": _MONITOR, "Preference-Applied": {
                  "description": "The `wait` preference, when given.",
                  "schema": {"type": "string"}}}},
        201: {"description": "Job created: asked for asynchronously, or longer than the "
              "synchronous wait.", "headers": {
            "Location": {"description": "URL of the job's status.",
                         "schema": {"type": "string"}},
            "Preference-Applied": {"description": "`respond-async` (and the `wait` "
                                   "preference, when given).",
                                   "schema": {"type": "string"}}}},
        404: _OGC_404,
        **problem_responses(400, 401, 413, 415, 422, 429, 507),
        500: {"model": ProblemDetails, "description": "Executed synchronously, the job failed "
              "for a limit or an internal error (a job that cannot register its input "
              "answers 422): its `error`, and the job in a `Link` header (`rel=monitor`).",
              "headers": {"Link": _MONITOR}},
    },
    openapi_extra={"requestBody": {"required": True, "content": {
        JSON: {"schema": {"$ref": "#/components/schemas/ExecuteRequest"}}}}},
)
async def execute(
    request: Request,
    response: Response,
    services: ServicesDep,
    client: ClientDep,
    process_id: Annotated[str, PathParam(alias="processId")],
    prefer: Annotated[
        list[str] | None,
        Header(description="`respond-async`: answer with the job at once; `wait=<seconds>`: "
               f"the longest a synchronous execution waits (at most {SYNC_WAIT_S})."),
    ] = None,
    idempotency_key: Annotated[
        str | None,
        Header(description="Client-chosen key; the same key with the same request returns the "
               "same job."),
    ] = None,
) -> Any:
    _check_process(process_id)

    async def receive(staging: Path) -> ReceivedForm:
        return await _receive_execute(request, services, staging)

    try:
        job, created = await jobs.submit(request, services, client, idempotency_key, receive)
    except Problem as problem:
        raise _as_input(problem) from None
    location = f"{_root(request)}/jobs/{job.id}"
    replayed = {} if created else {"Idempotent-Replayed": "true"}
    wanted = preferences(prefer or [])
    applied = ["respond-async"]
    if "respond-async" not in wanted:
        wait, waited = _sync_wait(wanted)
        finished = await _finished(request, services, job, wait)
        monitor = {"Link": f'<{location}>; rel="monitor"', **replayed}
        if waited:
            monitor["Preference-Applied"] = ", ".join(waited)
        if finished is not None and finished.status == JobStatus.successful:
            results = _results(request, services, finished)
            return JSONResponse(results.model_dump(mode="json", exclude_none=True),
                                headers=monitor)
        if finished is not None and finished.status == JobStatus.failed and finished.error:
            problem = _failure(finished)
            problem.headers.update(monitor)
            raise problem
        if finished is not None:
            job = finished  # dismissed while waiting: its status says so
        applied += waited
    response.headers["Location"] = location
    response.headers["Preference-Applied"] = ", ".join(applied)
    response.headers.update(replayed)
    return status_info(job, request)


# --- jobs -------------------------------------------------------------------------------------


def status_info(job: Job, request: Request) -> OgcStatusInfo:
    """The OGC status of ``job``: its links, the /v1 document as ``alternate`` and, once
    successful, the results."""
    links = [
        _link(request, f"/jobs/{job.id}", "self", "This job"),
        OgcLink(href=jobs.job_href(request, job.id), rel="alternate", type=JSON,
                title="The job's full status document (quality, options, error)"),
    ]
    if job.status == JobStatus.successful:
        links.append(_link(request, f"/jobs/{job.id}/results", f"{REL}results", "The results"))
    running = job.status == JobStatus.running
    return OgcStatusInfo(
        jobID=job.id,
        processID=PROCESS_ID,
        status=job.status,
        message=(job.stage if running else job.message) or None,
        created=job.created,
        started=job.started,
        finished=job.finished,
        updated=job.updated,
        progress=int(job.progress),
        links=links,
    )


def _failure(job: Job) -> Problem:
    """The error of a failed job, with its status (the standard answers the reason of the
    failure)."""
    error = dict(job.error or {})
    status = error.pop("status", 500)
    slug = str(error.pop("type", "")).removeprefix(TYPE_PREFIX) or "internal-error"
    title = error.pop("title", "Job failed")
    detail = error.pop("detail", None) or job.message or "the job failed"
    field = error.pop("field", None)
    error.pop("instance", None)
    return Problem(status if isinstance(status, int) and status >= 400 else 500, slug, title,
                   detail, field, job_id=job.id, **error)


def _job(services: Services, job_id: str, client: str | None) -> Job:
    job = jobs.visible_job(services, job_id, client)
    if job is None:
        raise OgcProblem(404, "no-such-job", "No such job", f"no job {job_id!r}")
    return job


SCAN_PAGE = 500
"""Jobs read from the store at a time when the list is filtered by ``datetime`` or duration,
which the store does not select by."""


def _instant(value: str) -> datetime:
    parsed = datetime.fromisoformat(value)
    if parsed.tzinfo is None:
        raise ValueError("no time zone")
    return parsed


def _interval(value: str) -> tuple[datetime | None, datetime | None]:
    """The ``datetime`` parameter as its inclusive bounds (None for an open end)."""
    try:
        if "/" not in value:
            return _instant(value), _instant(value)
        start, end = (None if b in ("", "..") else _instant(b) for b in value.split("/"))
        if start is None and end is None:
            raise ValueError("both ends open")
        if start is not None and end is not None and start > end:
            raise ValueError("the end is before the start")
    except ValueError:
        raise invalid_input(
            f"datetime: {value!r} is neither an RFC 3339 date-time with its time zone nor an "
            "interval start/end of them ('..' or nothing for an open end)", "datetime"
        ) from None
    return start, end


def duration(job: Job, now: datetime) -> float | None:
    """How long ``job`` has run (running) or ran (finished), seconds; None for a job that has
    not started or whose times are not all known."""
    if job.started is None:
        return None
    if job.status == JobStatus.running:
        return (now - job.started).total_seconds()
    if job.status in FINISHED and job.finished is not None:
        return (job.finished - job.started).total_seconds()
    return None


def _scan(services: Services, statuses: list[JobStatus], owner: str | None,
          keep: Callable[[Job], bool], since: datetime | None, limit: int, offset: int
          ) -> tuple[list[Job], bool]:
    """A page (``limit`` after ``offset``) of the jobs ``keep`` selects, newest first, and
    whether more follow; none created before ``since`` is read beyond the first."""
    found: list[Job] = []
    skip, at = offset, 0
    while True:
        batch, matched = services.store.list(statuses, limit=SCAN_PAGE, offset=at, owner=owner)
        for job in batch:
            if since is not None and job.created < since:
                return found, False  # newest first: every further job is older
            if not keep(job):
                continue
            if skip:
                skip -= 1
            elif len(found) == limit:
                return found, True
            else:
                found.append(job)
        at += len(batch)
        if not batch or at >= matched:
            return found, False


@router.get(
    "/jobs",
    response_model=OgcJobList,
    response_model_exclude_none=True,
    summary="Jobs",
    description="The client's jobs (the same as GET /v1/jobs), newest first, a page at a time, "
    "selected as in the job-list class of OGC API - Processes: by status, process, type, "
    "creation time and duration. The `next` link gives the following page.",
    responses=problem_responses(401, 422),
)
def list_jobs(
    request: Request,
    services: ServicesDep,
    client: ClientDep,
    status: Annotated[list[JobStatus] | None, Query(description="Only these statuses.")] = None,
    process_id: Annotated[
        list[str] | None, Query(alias="processID", description="Only jobs of these processes.")
    ] = None,
    type: Annotated[list[str] | None, Query(
        description="Only jobs of these types (`process`: all the jobs of this service).")] = None,
    when: Annotated[str | None, Query(
        alias="datetime",
        description="Only jobs created at this RFC 3339 date-time (with its time zone), or in "
        "this interval: `start/end`, `../end`, `start/..` (bounds included).",
        examples=["2026-11-24T00:00:00Z/.."])] = None,
    min_duration: Annotated[int | None, Query(
        alias="minDuration", ge=0,
        description="Only jobs that ran (finished) or have run (running) at least this many "
        "seconds from their start; jobs not started are left out, and without `status` only "
        "running and finished jobs are considered.")] = None,
    max_duration: Annotated[int | None, Query(
        alias="maxDuration", ge=0,
        description="Only jobs that ran or have run at most this many seconds (as "
        "`minDuration`).")] = None,
    limit: Annotated[int, Query(ge=1, le=10000, description="Jobs per page.")] = 10,
    offset: Annotated[
        int, Query(ge=0, le=2**53 - 1, description="Jobs to skip (newest first).")
    ] = 0,
) -> OgcJobList:
    statuses = status or []
    start, end = _interval(when) if when is not None else (None, None)
    timed = min_duration is not None or max_duration is not None
    if (process_id and PROCESS_ID not in process_id) or (type and "process" not in type):
        found, more = [], False
    elif when is not None or timed:
        now = utcnow()

        def keep(job: Job) -> bool:
            if end is not None and job.created > end:
                return False
            if not timed:
                return True
            took = duration(job, now)
            return took is not None and (min_duration is None or took >= min_duration) and (
                max_duration is None or took <= max_duration)

        found, more = _scan(services, statuses, client, keep, start, limit, offset)
    else:
        found, matched = services.store.list(statuses, limit=limit, offset=offset, owner=client)
        more = offset + len(found) < matched

    def page(at: int) -> str:
        query: list[tuple[str, Any]] = [("status", s.value) for s in statuses]
        query += [("processID", p) for p in process_id or []]
        query += [("type", t) for t in type or []]
        for name, value in (("datetime", when), ("minDuration", min_duration),
                            ("maxDuration", max_duration)):
            if value is not None:
                query.append((name, value))
        query += [("limit", limit), ("offset", at)]
        return f"/jobs?{urlencode(query)}"

    links = [_link(request, page(offset), "self", "This page")]
    if more:
        links.append(_link(request, page(offset + limit), "next", "Next page"))
    if offset > 0:
        links.append(_link(request, page(max(0, offset - limit)), "prev", "Previous page"))
    return OgcJobList(jobs=[status_info(j, request) for j in found], links=links)


@router.get(
    "/jobs/{jobId}",
    response_model=OgcStatusInfo,
    response_model_exclude_none=True,
    summary="Status of a job",
    description="Status and progress of a job; once successful, a link to its results.",
    responses={404: _OGC_404, **problem_responses(401)},
)
def get_job(
    request: Request,
    services: ServicesDep,
    client: ClientDep,
    job_id: Annotated[str, PathParam(alias="jobId")],
) -> OgcStatusInfo:
    return status_info(_job(services, job_id, client), request)


@router.delete(
    "/jobs/{jobId}",
    response_model=OgcStatusInfo,
    response_model_exclude_none=True,
    summary="Dismiss a job",
    description="Cancel a queued or running job and remove its files (as DELETE /v1/jobs/{id}); "
    "answers the job's status, dismissed.",
    responses={404: _OGC_404, **problem_responses(401)},
)
def dismiss_job(
    request: Request,
    services: ServicesDep,
    client: ClientDep,
    job_id: Annotated[str, PathParam(alias="jobId")],
) -> OgcStatusInfo:
    jobs.dismiss(services, _job(services, job_id, client))
    return status_info(_job(services, job_id, client), request)


@router.get(
    "/jobs/{jobId}/results",
    response_model=Results,
    response_model_exclude_none=True,
    summary="Results of a job",
    description="Each output of a successful job by reference: a link to the file, with its "
    "media type. A job that has not succeeded answers 404 (`result-not-ready`); a failed job "
    "answers its error.",
    responses={
        404: _OGC_404,
        **problem_responses(401),
        **{code: {"model": ProblemDetails, "description": f"The job failed: its `error`, {why}."}
           for code, why in ((422, "the input could not be registered"),
                             (500, "a limit or an internal error"))},
    },
)
def get_results(
    request: Request,
    services: ServicesDep,
    client: ClientDep,
    job_id: Annotated[str, PathParam(alias="jobId")],
) -> Results:
    job = _job(services, job_id, client)
    if job.status == JobStatus.failed and job.error:
        raise _failure(job)
    if job.status != JobStatus.successful:
        raise OgcProblem(404, "result-not-ready", "Result not ready",
                         result_not_ready(job.id, job.status.value).detail,
                         job_id=job.id, job_status=job.status.value)
    return _results(request, services, job)


def _results(request: Request, services: Services, job: Job) -> Results:
    """The results document of the successful ``job``: a link to each of its result files."""
    base = jobs.job_href(request, job.id)
    return Results({
        name: OgcLink(href=f"{base}/{RESULTS[name].route}", type=RESULTS[name].media_type,
                      title=RESULTS[name].title)
        for name in services.storage.result_names(job.id)
    })
