"""System resources: the options of a job, health, readiness and metrics."""

from __future__ import annotations

import functools
import logging
from typing import Any

from fastapi import APIRouter, Depends
from fastapi.responses import PlainTextResponse, Response
from pydantic import BaseModel

from pwlreg.core.options import RegistrationOptions
from pwlreg.service.auth import get_client
from pwlreg.service.deps import ServicesDep
from pwlreg.service.metrics import CONTENT_TYPE
from pwlreg.service.problems import Problem, problem_responses
from pwlreg.service.schemas import Health, OptionInfo, Readiness

log = logging.getLogger(__name__)

router = APIRouter(tags=["system"])


def describe_options(model: type[BaseModel] = RegistrationOptions) -> list[OptionInfo]:
    """Every field of the options model with its type, default, bounds and help text, read from
    the model's JSON schema (the options are declared once, in ``core.options``)."""
    schema = model.model_json_schema()
    infos = []
    for name, prop in schema["properties"].items():
        field = model.model_fields[name]
        choices = prop.get("enum")
        json_type = prop.get("type")
        if json_type is None and choices is not None:
            json_type = _json_type(choices[0])
        infos.append(
            OptionInfo(
                name=name,
                type=json_type,
                default=field.get_default(call_default_factory=True),
                minimum=prop.get("minimum"),
                maximum=prop.get("maximum"),
                exclusive_minimum=prop.get("exclusiveMinimum"),
                exclusive_maximum=prop.get("exclusiveMaximum"),
                choices=choices,
                help=prop.get("description", ""),
            )
        )
    return infos


def _json_type(value: Any) -> str:
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int):
        return "integer"
    if isinstance(value, float):
        return "number"
    return "string"


@functools.cache
def _options() -> list[OptionInfo]:
    return describe_options()


@router.get(
    "/v1/options",
    response_model=list[OptionInfo],
    summary="Options of a job",
    description="Every option a job accepts in its `options` object, with type, default, bounds "
    "and help text (NodeODM's /options is the model).",
    dependencies=[Depends(get_client)],
    responses=problem_responses(401),
)
def list_options() -> list[OptionInfo]:
    return _options()


@router.get("/healthz", response_model=Health, summary="Liveness",
            description="200 while the process answers.")
def healthz() -> Health:
    return Health(status="ok")


@router.get(
    "/readyz",
    response_model=Readiness,
    summary="Readiness",
    description="200 when the database answers, the queue dispatches and the data directory is "
    "writable; 503 with the failed checks otherwise.",
    responses=problem_responses(503),
)
def readyz(services: ServicesDep) -> Readiness:
    checks = {"database": False, "queue": False, "storage": False}
    try:
        checks["database"] = services.store.ping()
    except Exception as exc:  # noqa: BLE001 (a failed check, reported below)
        log.warning("readiness: database unreachable: %s", exc)
    checks["queue"] = services.queue.is_ready()
    checks["storage"] = services.storage.is_writable()
    if not all(checks.values()):
        failed = ", ".join(k for k, ok in checks.items() if not ok)
        raise Problem(503, "not-ready", "Not ready", f"failed checks: {failed}", checks=checks)
    return Readiness(status="ready", checks=checks)


@router.get(
    "/metrics",
    response_class=PlainTextResponse,
    summary="Prometheus metrics",
    description="In the Prometheus text format: jobs by status, queue depth and workers (read "
    "from the store when scraped), jobs submitted and submissions refused per client, the job "
    "duration histogram by final status and the stage duration histogram (seconds per stage of "
    "successful jobs). The README lists every metric.",
    responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format."},
               **problem_responses(401)},
    dependencies=[Depends(get_client)],
)
def metrics(services: ServicesDep) -> Response:
    return Response(services.metrics.render(), media_type=CONTENT_TYPE)
