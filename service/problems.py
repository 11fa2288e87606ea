"""Problem documents (RFC 9457, ``application/problem+json``): the one place that maps errors to
HTTP answers.

Every error answer of the API is a problem document with ``type``, ``title``, ``status``,
``detail`` and, when one input is at fault, ``field`` (``reference``, ``moving``, ``points``,
``options.<name>``, a query parameter or a header). The ``type`` URIs are URNs
(``urn:pwlreg:problem:<slug>``) listed in the README.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from pwlreg.core.errors import ImageTooLargeError, InputError, UnsupportedMediaError
from pwlreg.service.schemas import ProblemDetails

log = logging.getLogger(__name__)

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_PREFIX = "urn:pwlreg:problem:"


def problem_document(
    slug: str, title: str, status: int, detail: str, field: str | None = None, **extra: Any
) -> dict[str, Any]:
    """A problem document as a JSON-ready dict, for the errors stored with a failed job (the
    worker's and the store's): the same shape as every error answer of the API."""
    return Problem(status, slug, title, detail, field, **extra).to_dict()


class Problem(Exception):
    """An error answer, raised anywhere in the API and rendered by the installed handler.

    Parameters
    ----------
    status : int
        HTTP status code.
    slug : str
        Short name of the problem type; the ``type`` member is ``urn:pwlreg:problem:<slug>``.
    title : str
        Short summary of the problem type (the same for every occurrence).
    detail : str
        Explanation of this occurrence, saying what to change.
    field : str, optional
        The input at fault.
    headers : dict, optional
        Extra response headers (e.g. ``Retry-After``).
    **extra
        Further members of the document (e.g. ``errors``, ``job_status``).
    """

    def __init__(
        self,
        status: int,
        slug: str,
        title: str,
        detail: str,
        field: str | None = None,
        headers: dict[str, str] | None = None,
        **extra: Any,
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.slug = slug
        self.title = title
        self.detail = detail
        self.field = field
        self.headers = headers or {}
        self.extra = extra

    def to_dict(self) -> dict[str, Any]:
        """The problem document as a JSON-ready dict."""
        doc: dict[str, Any] = {
            "type": TYPE_PREFIX + self.slug,
            "title": self.title,
            "status": self.status,
            "detail": self.detail,
        }
        if self.field is not None:
            doc["field"] = self.field
        doc.update(self.extra)
        return doc

    def response(self, instance: str | None = None) -> JSONResponse:
        """The problem as an ``application/problem+json`` response."""
        doc = self.to_dict()
        if instance is not None:
            doc.setdefault("instance", instance)
        return JSONResponse(
            doc, status_code=self.status, media_type=PROBLEM_MEDIA_TYPE, headers=self.headers
        )


# --- constructors of the problems the API raises -------------------------------------------


def not_found(detail: str) -> Problem:
    return Problem(404, "not-found", "Not found", detail)


def invalid_input(detail: str, field: str | None = None, **extra: Any) -> Problem:
    return Problem(422, "invalid-input", "Invalid input", detail, field, **extra)


def malformed_request(detail: str, field: str | None = None) -> Problem:
    return Problem(400, "malformed-request", "Malformed request", detail, field)


def unsupported_media(detail: str, field: str | None = None) -> Problem:
    return Problem(415, "unsupported-media-type", "Unsupported media type", detail, field)


def image_too_large(detail: str, field: str | None = None) -> Problem:
    return Problem(422, "image-too-large", "Image too large", detail, field)


def upload_too_large(detail: str, field: str | None = None) -> Problem:
    return Problem(413, "upload-too-large", "Upload too large", detail, field)


def idempotency_conflict(detail: str, job_id: str) -> Problem:
    return Problem(
        422,
        "idempotency-key-reused",
        "Idempotency key reused",
        detail,
        "Idempotency-Key",
        job_id=job_id,
    )


def insufficient_storage(detail: str) -> Problem:
    return Problem(507, "insufficient-storage", "Insufficient storage", detail)


def too_many_jobs(detail: str, retry_after: int) -> Problem:
    return Problem(
        429, "too-many-jobs", "Too many queued jobs", detail,
        headers={"Retry-After": str(retry_after)}, retry_after=retry_after,
    )


def result_not_ready(job_id: str, status: str) -> Problem:
    detail = {
        "accepted": "the job is waiting for a worker; poll the job until its status is "
        "'successful'",
        "running": "the job is running; poll the job until its status is 'successful'",
        "failed": "the job failed, it has no results; the job's 'error' member says why",
        "dismissed": "the job was dismissed and its files removed",
    }.get(status, f"the job is {status}")
    return Problem(
        409, "result-not-ready", "Result not available", detail, job_id=job_id, job_status=status
    )


def from_input_error(exc: InputError) -> Problem:
    """The problem for an error of :mod:`core` about the input: 415 for bytes that are not an
    image of a supported kind (or a truncated or damaged one), 422 for everything else (too
    many pixels, bad points, ...)."""
    field = getattr(exc, "field", None)
    if isinstance(exc, UnsupportedMediaError):
        return unsupported_media(str(exc), field)
    if isinstance(exc, ImageTooLargeError):
        return image_too_large(str(exc), field)
    return invalid_input(str(exc), field)


def _loc_to_field(loc: tuple[Any, ...] | list[Any], prefix: str | None) -> str:
    parts = [str(p) for p in loc if p not in ("body", "__root__")]
    if prefix:
        parts.insert(0, prefix)
    return ".".join(parts) if parts else (prefix or "")


def from_validation_error(exc: ValidationError, prefix: str | None = None) -> Problem:
    """The 422 problem of a pydantic validation error, ``field`` naming the first wrong field
    (``prefix.<name>``) and ``errors`` listing all of them."""
    errors = [
        {"field": _loc_to_field(e["loc"], prefix), "message": e["msg"]} for e in exc.errors()
    ]
    first = errors[0] if errors else {"field": prefix, "message": "invalid"}
    detail = "; ".join(f"{e['field']}: {e['message']}" for e in errors) or str(exc)
    return invalid_input(detail, first["field"] or None, errors=errors)


# --- OpenAPI ---------------------------------------------------------------------------------

_RESPONSE_TEXT = {
    400: "Malformed request body.",
    401: "The server has API keys and the request has no `Authorization: Bearer <key>` header, "
    "a malformed one or an unknown key (`WWW-Authenticate: Bearer`).",
    404: "No such job (or a job of another client).",
    409: "The job has not succeeded (yet); no result.",
    413: "A part of the upload is over the size limit.",
    415: "Not multipart/form-data, or a file that is not an image of a supported kind, or a "
    "truncated or damaged one.",
    422: "Invalid input: missing or unknown part, bad options or points, image over the pixel "
    "limit, points outside their image, fewer than 3 pairs or collinear, bad query parameter, "
    "idempotency key reused with another request.",
    429: "Too many jobs waiting for a worker, in all or of this client; try again after "
    "`Retry-After` seconds.",
    503: "Not ready: the failed checks are listed in `checks`.",
    507: "Not enough free disk space for the upload; nothing of it was kept.",
}


def problem_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI description of the problem answers ``codes`` of a route (the media type is set
    to ``application/problem+json`` when the document is built)."""
    return {code: {"model": ProblemDetails, "description": _RESPONSE_TEXT[code]} for code in codes}


# --- handlers ------------------------------------------------------------------------------


def _instance(request: Request) -> str:
    return request.url.path


async def _problem_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, Problem)
    return exc.response(_instance(request))


async def _request_validation_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = []
    for e in exc.errors():
        loc = list(e.get("loc", ()))
        # FastAPI's loc starts with where the value came from: query, path, header, body.
        where = loc.pop(0) if loc and loc[0] in ("query", "path", "header", "body") else None
        if where in ("query", "header"):
            loc = [p for p in loc if not isinstance(p, int)]  # status.0 -> status
        name = ".".join(str(p) for p in loc)
        if where == "header":
            name = name.replace("_", "-").title()
        errors.append({"field": name or where or "request", "message": e.get("msg", "invalid")})
    detail = "; ".join(f"{e['field']}: {e['message']}" for e in errors) or "invalid request"
    first = errors[0]["field"] if errors else None
    return invalid_input(detail, first, errors=errors).response(_instance(request))


_HTTP_TITLES = {
    400: ("malformed-request", "Malformed request"),
    404: ("not-found", "Not found"),
    405: ("method-not-allowed", "Method not allowed"),
    406: ("not-acceptable", "Not acceptable"),
    413: ("upload-too-large", "Upload too large"),
    415: ("unsupported-media-type", "Unsupported media type"),
}


async def _http_exception_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    slug, title = _HTTP_TITLES.get(exc.status_code, ("http-error", "HTTP error"))
    detail = exc.detail if isinstance(exc.detail, str) else title
    if exc.status_code == 404 and detail == "Not Found":
        detail = f"no resource at {request.url.path}"
    problem = Problem(exc.status_code, slug, title, detail, headers=dict(exc.headers or {}))
    return problem.response(_instance(request))


async def _unexpected_handler(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unexpected error on %s %s", request.method, request.url.path)
    problem = Problem(
        500,
        "internal-error",
        "Internal error",
        "the server failed on this request; the error was logged",
    )
    return problem.response(_instance(request))


def install_problem_handlers(app: FastAPI) -> None:
    """Render every error of ``app`` as a problem document, including unexpected ones."""
    app.add_exception_handler(Problem, _problem_handler)
    app.add_exception_handler(RequestValidationError, _request_validation_handler)
    app.add_exception_handler(StarletteHTTPException, _http_exception_handler)
    app.add_exception_handler(Exception, _unexpected_handler)
