"""API models: the contract of the HTTP API, exported to ``openapi/openapi.json``.

Names and status words follow OGC API - Processes (status info, link objects). Times are
ISO 8601 in UTC; progress is a percentage (0-100).
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, RootModel

from pwlreg.core.options import RegistrationOptions
from pwlreg.service.store import JobStatus

_JOB_ID_EXAMPLE = "3f2c1e0a9b8d4c7e8f6a5b4c3d2e1f00"


class Options(RegistrationOptions):
    """Options of a registration job (every field optional in a request; the job document shows
    the effective values, defaults included). Declared once in ``core.options``."""

    model_config = ConfigDict(
        title="Options",
        json_schema_extra={
            "examples": [{"cost": "mi", "optimizer": "greedy", "epsilon": 0.01, "bins": 16}]
        },
    )


class Link(BaseModel):
    """A link object (OGC API / RFC 8288 style)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "href": f"/v1/jobs/{_JOB_ID_EXAMPLE}/mesh",
                    "rel": "http://www.opengis.net/def/rel/ogc/1.0/results",
                    "type": "application/json",
                    "title": "Meshes, swaps and matching results",
                }
            ]
        }
    )

    href: str = Field(
        description="Target of the link, a path relative to the server root (an absolute URL "
        "in a webhook delivery).",
        examples=[f"/v1/jobs/{_JOB_ID_EXAMPLE}"],
    )
    rel: str = Field(description="Relation type.", examples=["self"])
    type: str | None = Field(
        None, description="Media type of the target.", examples=["application/json"]
    )
    title: str | None = Field(
        None, description="Human-readable title of the target.", examples=["This job"]
    )


class FieldError(BaseModel):
    """One wrong input of a request."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [{"field": "options.bins", "message": "Input should be less than or "
                          "equal to 256"}]
        }
    )

    field: str = Field(description="Name of the input.", examples=["options.bins"])
    message: str = Field(description="What is wrong with it.", examples=["Input should be ..."])


class ProblemDetails(BaseModel):
    """An error, as an RFC 9457 problem document (media type ``application/problem+json``)."""

    model_config = ConfigDict(
        extra="allow",
        json_schema_extra={
            "examples": [
                {
                    "type": "urn:pwlreg:problem:image-too-large",
                    "title": "Image too large",
                    "status": 422,
                    "detail": "moving has 100000000 pixels (10000x10000); the limit is "
                    "40000000",
                    "field": "moving",
                    "instance": "/v1/jobs",
                }
            ]
        },
    )

    type: str = Field(
        description="URI of the problem type, ``urn:pwlreg:problem:<slug>``.",
        examples=["urn:pwlreg:problem:invalid-input"],
    )
    title: str = Field(description="Short summary of the problem type.", examples=["Invalid input"])
    status: int = Field(description="HTTP status code of this occurrence.", examples=[422])
    detail: str = Field(
        description="Explanation of this occurrence.", examples=["options.bins: Input should be "
                                                                 "less than or equal to 256"]
    )
    instance: str | None = Field(
        None, description="Path of the request that failed.", examples=["/v1/jobs"]
    )
    field: str | None = Field(
        None,
        description="The input at fault: a form part (reference, moving, points), an option "
        "(options.<name>), a query parameter or a header.",
        examples=["options.bins"],
    )
    errors: list[FieldError] | None = Field(
        None, description="Every wrong input, when there are several."
    )


class WebhookInfo(BaseModel):
    """The webhook of a job and the state of its delivery."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "success_uri": "https://example.org/pwlreg-hook",
                    "failed_uri": "https://example.org/pwlreg-hook",
                    "event": "successful",
                    "state": "delivered",
                    "attempts": 1,
                    "last_attempt": "2026-01-01T12:00:10Z",
                    "last_error": None,
                    "delivery_id": "9a0c6f1e2b3d4c5e6f708192a3b4c5d6",
                }
            ]
        }
    )

    success_uri: str | None = Field(
        description="Where a successful job is announced (the callback URL, or successUri).",
        examples=["https://example.org/pwlreg-hook"],
    )
    failed_uri: str | None = Field(
        description="Where a failed or dismissed job is announced (the callback URL, or "
        "failedUri).",
        examples=["https://example.org/pwlreg-hook"],
    )
    event: JobStatus | None = Field(
        None,
        description="The end the last delivery announces (the job's status then); None while "
        "the job has not ended.",
        examples=["successful"],
    )
    state: Literal["waiting", "pending", "delivered", "failed", "skipped"] = Field(
        description="waiting (the job has not ended), pending (being sent or waiting for a "
        "retry), delivered (a 2xx answer), failed (every attempt failed), skipped (no URL for "
        "this end).",
        examples=["delivered"],
    )
    attempts: int = Field(description="Attempts of the delivery so far.", examples=[1])
    last_attempt: datetime | None = Field(
        None, description="When the last attempt ended (UTC)."
    )
    last_error: str | None = Field(
        None,
        description="Why the last attempt failed (HTTP status or connection error).",
        examples=["HTTP 500"],
    )
    delivery_id: str | None = Field(
        None,
        description="Identifier of the delivery, sent as X-Pwlreg-Delivery with every attempt.",
        examples=["9a0c6f1e2b3d4c5e6f708192a3b4c5d6"],
    )


class StatusInfo(BaseModel):
    """Status of one job (OGC API - Processes ``statusInfo``)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": _JOB_ID_EXAMPLE,
                    "type": "process",
                    "processID": "register",
                    "status": "running",
                    "stage": "optimizing",
                    "progress": 57,
                    "message": None,
                    "attempts": 1,
                    "created": "2026-01-01T12:00:00Z",
                    "started": "2026-01-01T12:00:01Z",
                    "finished": None,
                    "updated": "2026-01-01T12:00:09Z",
                    "options": {"cost": "mi", "optimizer": "greedy"},
                    "has_points": True,
                    "links": [
                        {
                            "href": f"/v1/jobs/{_JOB_ID_EXAMPLE}",
                            "rel": "self",
                            "type": "application/json",
                            "title": "This job",
                        }
                    ],
                    "error": None,
                }
            ]
        }
    )

    id: str = Field(description="Identifier of the job.", examples=[_JOB_ID_EXAMPLE])
    type: Literal["process"] = Field("process", description="Always 'process' (OGC).")
    processID: Literal["register"] = Field(  # noqa: N815 (OGC member name)
        "register", description="The process the job runs (OGC); pwlreg has one."
    )
    status: JobStatus = Field(
        description="accepted (waiting for a worker), running, successful, failed or dismissed "
        "(cancelled by the client).",
        examples=["running"],
    )
    stage: Literal["matching", "triangulating", "optimizing", "rendering"] | None = Field(
        None,
        description="Stage of a running job: matching (conjugate points), triangulating "
        "(initial Delaunay mesh), optimizing (edge swaps), rendering (registered image).",
        examples=["optimizing"],
    )
    progress: int = Field(
        ge=0, le=100, description="Estimated completion in percent.", examples=[57]
    )
    message: str | None = Field(
        None,
        description="Human-readable note: the one-line summary of a successful job, the reason "
        "of a failure, or why the job was requeued.",
        examples=["42 vertices, 68 triangles, 5 swaps, NMI 1.182 -> 1.214"],
    )
    attempts: int = Field(
        description="Attempts started so far (a job is retried when its worker dies).",
        examples=[1],
    )
    created: datetime = Field(description="When the job was accepted (UTC).")
    started: datetime | None = Field(
        None, description="When the last attempt started (UTC)."
    )
    finished: datetime | None = Field(
        None, description="When the job succeeded, failed or was dismissed (UTC)."
    )
    updated: datetime = Field(description="Last change of this document (UTC).")
    options: dict[str, Any] = Field(
        description="Effective options of the job (see GET /v1/options), defaults included.",
        examples=[{"cost": "mi", "optimizer": "greedy"}],
    )
    has_points: bool = Field(
        description="True if the client sent conjugate points; otherwise they are matched "
        "automatically.",
        examples=[True],
    )
    quality: dict[str, Any] | None = Field(
        None,
        description="Verdict on the result, once it exists: 'verdict' (good, doubtful or "
        "unreliable), 'reasons' (why it is not good) and the figures behind it (points kept "
        "and dropped by cause, inlier share, coverage of the reference frame, MI and NMI "
        "before and after, global agreement peak, share of the textured area whose local "
        "consistency is low). Also set on a failed job when the failure is a verdict on the "
        "images: 'unreliable' with the reason, for on_unreliable=fail and for a pair in which "
        "too few reliable conjugate points were found.",
        examples=[{"verdict": "good", "reasons": [], "points": 412, "inlier_share": 0.84,
                   "measured_coverage": 0.68, "mesh_coverage": 1.0, "global_peak": 0.61}],
    )
    links: list[Link] = Field(
        description="The job itself and, once successful, every result with its media type."
    )
    error: ProblemDetails | None = Field(
        None, description="Why the job failed, as a problem document (failed jobs only)."
    )
    webhook: WebhookInfo | None = Field(
        None,
        description="The job's webhook (callback or subscriber) and the state of its delivery; "
        "None without one.",
    )


class JobList(BaseModel):
    """One page of jobs, newest first."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "jobs": [],
                    "numberMatched": 0,
                    "numberReturned": 0,
                    "links": [
                        {
                            "href": "/v1/jobs?limit=20&offset=0",
                            "rel": "self",
                            "type": "application/json",
                            "title": "This page",
                        }
                    ],
                }
            ]
        }
    )

    jobs: list[StatusInfo] = Field(description="The jobs of this page, newest first.")
    numberMatched: int = Field(  # noqa: N815 (OGC member name)
        description="Number of jobs matching the filter.", examples=[42]
    )
    numberReturned: int = Field(  # noqa: N815 (OGC member name)
        description="Number of jobs in this page.", examples=[20]
    )
    links: list[Link] = Field(description="This page and the next and previous pages.")


class OptionInfo(BaseModel):
    """One option of a registration job (NodeODM ``/options`` style)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "name": "bins",
                    "type": "integer",
                    "default": 16,
                    "minimum": 2,
                    "maximum": 256,
                    "exclusive_minimum": None,
                    "exclusive_maximum": None,
                    "choices": None,
                    "help": "Grey-level bins per image of the joint histogram (M).",
                }
            ]
        }
    )

    name: str = Field(description="Name of the option in the options object.", examples=["bins"])
    type: Literal["integer", "number", "string", "boolean"] = Field(
        description="JSON type of the value.", examples=["integer"]
    )
    default: Any = Field(description="Value used when the option is not given.", examples=[16])
    minimum: float | None = Field(None, description="Smallest allowed value.", examples=[2])
    maximum: float | None = Field(None, description="Largest allowed value.", examples=[256])
    exclusive_minimum: float | None = Field(
        None, description="The value must be greater than this.", examples=[None]
    )
    exclusive_maximum: float | None = Field(
        None, description="The value must be smaller than this.", examples=[None]
    )
    choices: list[Any] | None = Field(
        None, description="Allowed values, for options with a fixed set.", examples=[["mi", "ncc"]]
    )
    help: str = Field(description="What the option does, with its unit.")


class Health(BaseModel):
    """Liveness of the process."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"status": "ok"}]})

    status: Literal["ok"] = Field(description="Always 'ok' when the process answers.")


class Readiness(BaseModel):
    """Readiness: the database, the queue and the data directory are usable."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"status": "ready", "checks": {"database": True, "queue": True, "storage": True}}
            ]
        }
    )

    status: Literal["ready"] = Field(description="Always 'ready' (otherwise the answer is 503).")
    checks: dict[str, bool] = Field(
        description="Result of each check: database, queue, storage.",
        examples=[{"database": True, "queue": True, "storage": True}],
    )


# --- OGC API - Processes - Part 1: Core (OGC 18-062r2) -----------------------------------------

_PROCESS_ID = "pwl-registration"
_OGC_REL = "http://www.opengis.net/def/rel/ogc/1.0/"


class OgcLink(BaseModel):
    """A link object (OGC ``link.yaml``); absent members are left out of the document."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "href": "/processes/pwl-registration",
                    "rel": "self",
                    "type": "application/json",
                    "title": "This process",
                }
            ]
        }
    )

    href: str = Field(
        description="Target of the link, a path relative to the server root.",
        examples=["/processes"],
    )
    rel: str | None = Field(None, description="Relation type.", examples=["self"])
    type: str | None = Field(
        None, description="Media type of the target.", examples=["application/json"]
    )
    title: str | None = Field(None, description="Human-readable title of the target.")


class LandingPage(BaseModel):
    """The landing page of the OGC API (``landingPage.yaml``)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "title": "pwlreg",
                    "description": "Piecewise-linear image registration",
                    "links": [{"href": "/conformance", "rel": f"{_OGC_REL}conformance",
                               "type": "application/json", "title": "Conformance classes"}],
                }
            ]
        }
    )

    title: str = Field(description="Name of the service.", examples=["pwlreg"])
    description: str = Field(description="What the service does.")
    links: list[OgcLink] = Field(
        description="The API definition (service-desc, service-doc), the conformance "
        "declaration, the processes and the jobs."
    )


class ConformanceDeclaration(BaseModel):
    """The conformance classes the API implements (``confClasses.yaml``)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"conformsTo": ["http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/core"]}
            ]
        }
    )

    conformsTo: list[str] = Field(  # noqa: N815 (OGC member name)
        description="URIs of the conformance classes."
    )


class ProcessSummary(BaseModel):
    """A process as listed by ``/processes`` (``processSummary.yaml``)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": _PROCESS_ID,
                    "version": "0.1.0",
                    "title": "Piecewise-linear registration of an image pair",
                    "jobControlOptions": ["async-execute", "dismiss"],
                    "outputTransmission": ["reference"],
                    "links": [{"href": f"/processes/{_PROCESS_ID}", "rel": "self",
                               "type": "application/json", "title": "Process description"}],
                }
            ]
        }
    )

    id: str = Field(description="Identifier of the process.", examples=[_PROCESS_ID])
    version: str = Field(description="Version of the process (the service's).")
    title: str = Field(description="Title of the process.")
    description: str = Field(description="What the process does.")
    keywords: list[str] = Field(description="Keywords.")
    jobControlOptions: list[Literal["sync-execute", "async-execute", "dismiss"]] = Field(  # noqa: N815
        description="How the process may be executed: asynchronously only, and its jobs may "
        "be dismissed."
    )
    outputTransmission: list[Literal["value", "reference"]] = Field(  # noqa: N815
        description="How results are delivered: by reference (links to the files)."
    )
    links: list[OgcLink] = Field(description="The process description and its execution.")


class ParameterDescription(BaseModel):
    """An input or output of the process with the schema of its values."""

    model_config = ConfigDict(
        populate_by_name=True,
        json_schema_extra={
            "examples": [
                {
                    "title": "Reference image",
                    "description": "The image the moving image is registered onto.",
                    "minOccurs": 1,
                    "maxOccurs": 1,
                    "schema": {"type": "string", "contentEncoding": "binary",
                               "contentMediaType": "image/png"},
                }
            ]
        },
    )

    title: str = Field(description="Title of the input or output.")
    description: str = Field(description="What it is, with its units and conventions.")
    minOccurs: int | None = Field(  # noqa: N815 (OGC member name)
        None, description="Inputs: 1 if required, 0 if optional."
    )
    maxOccurs: int | None = Field(  # noqa: N815 (OGC member name)
        None, description="Inputs: the most values the input takes (1)."
    )
    value_schema: dict[str, Any] = Field(
        alias="schema",
        description="Schema of the values (an OpenAPI 3.0 schema object).",
    )


class ProcessDescription(ProcessSummary):
    """The full description of a process (``process.yaml``): its inputs and outputs."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": _PROCESS_ID,
                    "version": "0.1.0",
                    "title": "Piecewise-linear registration of an image pair",
                    "jobControlOptions": ["async-execute", "dismiss"],
                    "outputTransmission": ["reference"],
                    "inputs": {},
                    "outputs": {},
                    "links": [],
                }
            ]
        }
    )

    inputs: dict[str, ParameterDescription] = Field(
        description="The inputs: reference, moving (images), points and options."
    )
    outputs: dict[str, ParameterDescription] = Field(
        description="The outputs, one per result file of a registration."
    )


class ProcessList(BaseModel):
    """The processes of the service (``processList.yaml``)."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"processes": [], "links": [
            {"href": "/processes", "rel": "self", "type": "application/json"}]}]}
    )

    processes: list[ProcessSummary] = Field(description="Every process (pwlreg has one).")
    links: list[OgcLink] = Field(description="This document.")


class OutputSelection(BaseModel):
    """An output requested by an execute request (``output.yaml``)."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{"transmissionMode": "reference"}]},
    )

    format: dict[str, Any] | None = Field(
        None, description="Requested format; each output has one media type, which must match."
    )
    transmissionMode: Literal["value", "reference"] | None = Field(  # noqa: N815
        None, description="Only 'reference' is supported (the results are links to files)."
    )


class Subscriber(BaseModel):
    """Where the end of the job is announced (``subscriber.yaml``), as with /v1 webhooks."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [{"successUri": "https://example.org/done",
                          "failedUri": "https://example.org/failed"}]
        },
    )

    successUri: str | None = Field(  # noqa: N815 (OGC member name)
        None, description="POSTed the job's /v1 status document when it succeeds."
    )
    inProgressUri: str | None = Field(  # noqa: N815 (OGC member name)
        None, description="Accepted and ignored."
    )
    failedUri: str | None = Field(  # noqa: N815 (OGC member name)
        None, description="POSTed the job's /v1 status document when it fails or is dismissed."
    )


class ExecuteRequest(BaseModel):
    """An execute request (``execute.yaml``)."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {
                    "inputs": {
                        "reference": {"href": "https://data.example.org/reference.png",
                                      "type": "image/png"},
                        "moving": {"value": "iVBORw0KGgo...", "mediaType": "image/png"},
                        "points": {"value": {"reference": [[10, 12], [200, 15], [105, 180]],
                                             "moving": [[12, 11], [203, 17], [104, 184]]},
                                   "mediaType": "application/json"},
                        "options": {"bins": 32},
                    },
                    "response": "document",
                }
            ]
        },
    )

    inputs: dict[str, Any] = Field(
        description="The inputs by identifier. Images: a qualified value "
        '({"value": "<base64>", "mediaType": "image/png"}), a bare base64 string or a link '
        '({"href": ...}) to an origin the service reads from. points: a points object '
        '({"reference": [[x, y], ...], "moving": [[x, y], ...]}), bare or as a qualified '
        "value, a CSV text as a qualified value (mediaType text/csv) or a link. options: an "
        "options object, bare or as a qualified value."
    )
    outputs: dict[str, OutputSelection] | None = Field(
        None, description="Outputs to return; every output is returned whatever is named."
    )
    response: Literal["raw", "document"] | None = Field(
        None, description="Only 'document' is supported: the results are a JSON document."
    )
    subscriber: Subscriber | None = Field(
        None, description="Webhook URLs announcing the end of the job."
    )


class OgcStatusInfo(BaseModel):
    """Status of a job (``statusInfo.yaml``)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "jobID": _JOB_ID_EXAMPLE,
                    "processID": _PROCESS_ID,
                    "type": "process",
                    "status": "running",
                    "message": "optimizing",
                    "created": "2026-01-01T12:00:00Z",
                    "started": "2026-01-01T12:00:01Z",
                    "updated": "2026-01-01T12:00:09Z",
                    "progress": 57,
                    "links": [{"href": f"/jobs/{_JOB_ID_EXAMPLE}", "rel": "self",
                               "type": "application/json", "title": "This job"}],
                }
            ]
        }
    )

    jobID: str = Field(description="Identifier of the job.")  # noqa: N815 (OGC member name)
    processID: str = Field(description="The process the job runs.")  # noqa: N815
    type: Literal["process"] = Field("process", description="Always 'process'.")
    status: JobStatus = Field(
        description="accepted, running, successful, failed or dismissed."
    )
    message: str | None = Field(
        None,
        description="The stage of a running job, the summary of a successful one, the reason "
        "of a failure.",
    )
    created: datetime = Field(description="When the job was accepted (UTC).")
    started: datetime | None = Field(None, description="When the last attempt started (UTC).")
    finished: datetime | None = Field(None, description="When the job ended (UTC).")
    updated: datetime = Field(description="Last change of the job (UTC).")
    progress: int = Field(ge=0, le=100, description="Estimated completion in percent.")
    links: list[OgcLink] = Field(
        description="The job, its full /v1 status document (alternate: quality, options, "
        "error) and, once successful, its results."
    )


class OgcJobList(BaseModel):
    """One page of jobs, newest first (``jobList.yaml``)."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"jobs": [], "links": [
            {"href": "/jobs?limit=10&offset=0", "rel": "self", "type": "application/json"}]}]}
    )

    jobs: list[OgcStatusInfo] = Field(description="The jobs of this page, newest first.")
    links: list[OgcLink] = Field(description="This page and the next and previous pages.")


class Results(RootModel[dict[str, OgcLink]]):
    """The results of a successful job (``results.yaml``): each output by reference."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"mesh": {"href": f"/v1/jobs/{_JOB_ID_EXAMPLE}/mesh", "type": "application/json",
                          "title": "Meshes, swaps and matching results"}}
            ]
        }
    )
