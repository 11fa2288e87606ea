"""Command line: ``pwlreg serve``, ``pwlreg worker``, ``pwlreg register`` and ``pwlreg submit``.

``register`` runs a registration in this process; ``submit`` sends it to a running service and
downloads the results; ``serve`` runs the service; ``worker`` runs a Celery worker of a service
in scale-out mode. The option flags of ``register`` and
``submit`` are derived from :class:`core.options.RegistrationOptions` (declared once).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import time
import typing
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal, TextIO

from pydantic import BaseModel, ValidationError

from pwlreg.core.formats.points import GCPS_KEYWORD
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.results import RESULTS

DEFAULT_URL = "http://127.0.0.1:8000"
RESULTS_REL = "http://www.opengis.net/def/rel/ogc/1.0/results"
FINISHED = ("successful", "failed", "dismissed")
UNRELIABLE_EXIT = 3
"""Exit status of a registration refused as unreliable (``--on-unreliable fail``)."""


class CommandError(Exception):
    """A failure to report as one line on stderr, with exit status ``code``."""

    def __init__(self, message: str, code: int = 2) -> None:
        super().__init__(message)
        self.code = code


# --- option flags derived from the options model ---------------------------------------------


def add_option_arguments(
    parser: argparse.ArgumentParser, model: type[BaseModel] = RegistrationOptions
) -> None:
    """Add one ``--flag`` per field of ``model`` (``min_triangle_area`` ->
    ``--min-triangle-area``), with the field's choices, type, default and description."""
    group = parser.add_argument_group("registration options (see GET /v1/options)")
    for name, field in model.model_fields.items():
        annotation = field.annotation
        flag = "--" + name.replace("_", "-")
        default = field.get_default(call_default_factory=True)
        help_text = f"{field.description or ''} (default: {default})".strip()
        help_text = help_text.replace("%", "%%")
        kwargs: dict[str, Any] = {"dest": name, "default": None, "help": help_text}
        if typing.get_origin(annotation) is Literal:
            kwargs["choices"] = list(typing.get_args(annotation))
        elif annotation is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif annotation in (int, float, str):
            kwargs["type"] = annotation
            kwargs["metavar"] = name.upper()
        else:  # pragma: no cover (a new field type: accept JSON)
            kwargs["type"] = json.loads
            kwargs["metavar"] = "JSON"
        group.add_argument(flag, **kwargs)


def options_from_args(
    args: argparse.Namespace, model: type[BaseModel] = RegistrationOptions
) -> dict[str, Any]:
    """The options given on the command line (only those given)."""
    return {
        name: getattr(args, name)
        for name in model.model_fields
        if getattr(args, name, None) is not None
    }


def _validation_message(exc: ValidationError, prefix: str = "options") -> str:
    parts = []
    for error in exc.errors():
        loc = ".".join(str(p) for p in error["loc"])
        parts.append(f"{prefix}.{loc}: {error['msg']}" if loc else f"{prefix}: {error['msg']}")
    return "; ".join(parts)


# --- progress display ------------------------------------------------------------------------


class ProgressBar:
    """A one-line progress bar on a terminal, or one line per stage otherwise.

    Parameters
    ----------
    stream : text stream
        Where to draw (stderr by default).
    width : int
        Characters of the bar.
    """

    def __init__(self, stream: TextIO | None = None, width: int = 30) -> None:
        self.stream = stream or sys.stderr
        self.width = width
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.last: tuple[str, int] | None = None

    def show(self, label: str, percent: float) -> None:
        pct = int(max(0.0, min(100.0, percent)))
        if (label, pct) == self.last:
            return
        if self.tty:
            filled = round(self.width * pct / 100)
            bar = "#" * filled + "-" * (self.width - filled)
            self.stream.write(f"\r[{bar}] {pct:3d}% {label:<14}")
            self.stream.flush()
        elif self.last is None or self.last[0] != label:
            self.stream.write(f"{label} ...\n")
            self.stream.flush()
        self.last = (label, pct)

    def close(self) -> None:
        if self.tty and self.last is not None:
            self.stream.write("\n")
            self.stream.flush()


# --- register --------------------------------------------------------------------------------


def cmd_register(args: argparse.Namespace) -> int:
    """Register two image files locally and write the three result files."""
    from pwlreg.core.errors import InputError, UnreliableResultError
    from pwlreg.core.formats.geotiff import open_image
    from pwlreg.core.io import load_points
    from pwlreg.core.pipeline import STAGES
    from pwlreg.core.results import Sources, write_outputs
    from pwlreg.core.scaled import register

    bar = ProgressBar() if not args.quiet else None
    spans = {stage: i for i, stage in enumerate(STAGES)}

    def progress(stage: str, fraction: float) -> None:
        if bar is not None:
            bar.show(stage, 100.0 * (spans.get(stage, 0) + fraction) / len(STAGES))

    try:
        options = RegistrationOptions(**options_from_args(args))
        with contextlib.ExitStack() as stack:
            # A large TIFF is read window by window (pwlreg.core.scaled), anything else whole.
            threads = os.cpu_count() or 1
            reference = _closing(stack, open_image(args.reference, field="reference",
                                                   threads=threads))
            moving = _closing(stack, open_image(args.moving, field="moving", threads=threads))
            points = None
            if args.points:
                data = GCPS_KEYWORD if _own_gcps(args.points) else Path(args.points).read_bytes()
                points = load_points(data, reference=args.reference, moving=args.moving)
            result = register(reference, moving, points=points, options=options,
                              progress=progress)
        pictures = (None if hasattr(i, "close") else i for i in (reference, moving))
        write_outputs(result, args.out, sources=Sources(
            *pictures, Path(args.reference), Path(args.moving), threads=threads))
    except UnreliableResultError as exc:
        raise CommandError(str(exc), UNRELIABLE_EXIT) from None
    except InputError as exc:
        field = getattr(exc, "field", None)
        message = f"{field}: {exc}" if field and field not in str(exc) else str(exc)
        raise CommandError(message) from None
    except ValidationError as exc:
        raise CommandError(_validation_message(exc)) from None
    except OSError as exc:
        raise CommandError(f"{exc.filename or ''}: {exc.strerror or exc}".lstrip(": ")) from None
    finally:
        if bar is not None:
            bar.close()
    print(result.summary())
    return 0


def _closing(stack: contextlib.ExitStack, image: Any) -> Any:
    """``image``, closed with ``stack`` when it is a file read window by window."""
    return stack.enter_context(image) if hasattr(image, "close") else image


# --- submit ----------------------------------------------------------------------------------


def _problem_text(response: Any) -> str:
    try:
        doc = response.json()
    except ValueError:
        return f"HTTP {response.status_code}: {response.text[:200]}"
    if isinstance(doc, dict) and "title" in doc:
        field = f" [{doc['field']}]" if doc.get("field") else ""
        return f"HTTP {response.status_code} {doc['title']}{field}: {doc.get('detail', '')}"
    return f"HTTP {response.status_code}: {doc}"


def _own_gcps(points: str) -> bool:
    """Whether ``--points`` names the moving GeoTIFF's own GCPs: the word ``gcps``, unless a
    file has that name."""
    return points.lower() == GCPS_KEYWORD and not Path(points).exists()


def cmd_submit(args: argparse.Namespace) -> int:
    """Upload a pair to a service, follow the job with a progress bar, download the results."""
    import httpx

    try:
        options = RegistrationOptions(**options_from_args(args))
    except ValidationError as exc:
        raise CommandError(_validation_message(exc)) from None
    given = options.model_dump(exclude_unset=True, mode="json")
    out = Path(args.out)
    paths = {"reference": Path(args.reference), "moving": Path(args.moving)}
    fields = {"options": json.dumps(given)} if given else {}
    if args.points and _own_gcps(args.points):
        fields["points"] = GCPS_KEYWORD
    elif args.points:
        paths["points"] = Path(args.points)
    for name, path in paths.items():
        if not path.is_file():
            raise CommandError(f"{name}: no such file: {path}")
    out.mkdir(parents=True, exist_ok=True)
    headers = {"Idempotency-Key": args.idempotency_key} if args.idempotency_key else {}
    auth = {"Authorization": f"Bearer {args.api_key}"} if args.api_key else {}
    bar = None if args.quiet else ProgressBar()
    with httpx.Client(base_url=args.url, timeout=httpx.Timeout(60.0, connect=10.0),
                      headers=auth) as client:
        handles = {name: path.open("rb") for name, path in paths.items()}
        try:
            files = {name: (paths[name].name, fh) for name, fh in handles.items()}
            response = client.post("/v1/jobs", files=files, data=fields or None,
                                   headers=headers)
        except httpx.TransportError as exc:
            raise CommandError(f"cannot reach {args.url}: {exc}", 1) from None
        finally:
            for fh in handles.values():
                fh.close()
        if response.status_code != 201:
            raise CommandError(_problem_text(response), 1)
        location = response.headers["Location"]
        job = response.json()
        print(f"job {job['id']}: {args.url.rstrip('/')}{location}", file=sys.stderr)
        try:
            job = _follow(client, location, job, bar, args.poll_interval, args.timeout)
        except KeyboardInterrupt:
            if bar is not None:
                bar.close()
            print(f"interrupted; job {job['id']} goes on at {location}", file=sys.stderr)
            return 130
        if bar is not None:
            bar.close()
        if job["status"] != "successful":
            error = job.get("error") or {}
            reason = error.get("detail") or job.get("message") or job["status"]
            code = UNRELIABLE_EXIT if error.get("type", "").endswith(":unreliable-result") else 1
            raise CommandError(f"job {job['id']} {job['status']}: {reason}", code)
        files_by_route = {fmt.route: fmt.filename for fmt in RESULTS.values()}
        for link in job.get("links", []):
            if link.get("rel") != RESULTS_REL:
                continue
            route = link["href"].rstrip("/").rsplit("/", 1)[-1]
            target = out / files_by_route.get(route, route)
            with client.stream("GET", f"{location}/{route}") as result:
                if result.status_code != 200:
                    result.read()
                    raise CommandError(f"download of {route}: {_problem_text(result)}", 1)
                with target.open("wb") as fh:
                    for chunk in result.iter_bytes():
                        fh.write(chunk)
    print(job.get("message") or f"job {job['id']} successful")
    return 0


def _follow(
    client: Any,
    location: str,
    job: dict[str, Any],
    bar: ProgressBar | None,
    interval: float,
    timeout: float,
) -> dict[str, Any]:
    """Poll the job until it is finished; ride out a restarting server."""
    import httpx

    deadline = time.monotonic() + timeout
    while job["status"] not in FINISHED:
        if bar is not None:
            bar.show(job.get("stage") or job["status"], job.get("progress", 0))
        if time.monotonic() > deadline:
            raise CommandError(f"job {job['id']} not finished after {timeout:g} s", 1)
        time.sleep(interval)
        try:
            response = client.get(location)
        except httpx.TransportError:
            continue  # the service may be restarting; the job is not lost
        if response.status_code != 200:
            raise CommandError(_problem_text(response), 1)
        job = response.json()
    if bar is not None and job["status"] == "successful":
        bar.show("done", 100)
    return job


# --- serve -----------------------------------------------------------------------------------


def cmd_serve(args: argparse.Namespace) -> int:
    """Run the service with uvicorn (API, worker processes, SQLite, local files)."""
    import uvicorn

    from pwlreg.service.app import create_app
    from pwlreg.service.logs import configure_logging
    from pwlreg.service.settings import Settings

    overrides: dict[str, Any] = {}
    if args.data_dir is not None:
        overrides["data_dir"] = args.data_dir
    if args.workers is not None:
        overrides["workers"] = args.workers
    try:
        settings = Settings(**overrides)
    except ValidationError as exc:
        raise CommandError(_validation_message(exc, prefix="settings")) from None
    configure_logging(args.log_level.upper(), settings.log_format)
    uvicorn.run(
        create_app(settings),
        host=args.host,
        port=args.port,
        log_level=args.log_level,
        # JSON: uvicorn's records (errors, access log) go to the root handler too, one JSON
        # object per line; text keeps uvicorn's own format.
        **({"log_config": None} if settings.log_format == "json" else {}),
        timeout_graceful_shutdown=15,
    )
    return 0


# --- worker ----------------------------------------------------------------------------------


SCHEMA_WAIT_SECONDS = 120.0
"""How long ``pwlreg worker`` waits for the job database and for the API to upgrade its
schema (services started together: the database starts, then the API migrates)."""


def cmd_worker(args: argparse.Namespace) -> int:
    """Run a Celery worker of the scale-out mode: it takes jobs from the broker
    (PWLREG_BROKER_URL) and runs them against the job database (PWLREG_DATABASE_URL) and the
    shared data directory (PWLREG_DATA_DIR), as the embedded workers do."""
    from pwlreg.service.logs import configure_logging
    from pwlreg.service.settings import Settings
    from pwlreg.service.storage import open_storage

    overrides: dict[str, Any] = {}
    if args.data_dir is not None:
        overrides["data_dir"] = args.data_dir
    try:
        settings = Settings(**overrides)
    except ValidationError as exc:
        raise CommandError(_validation_message(exc, prefix="settings")) from None
    if not settings.broker_url:
        raise CommandError("no broker: set PWLREG_BROKER_URL (e.g. redis://127.0.0.1:6379/0)")
    if args.concurrency is not None and args.concurrency < 1:
        raise CommandError("--concurrency must be at least 1")
    level = args.log_level.upper()
    configure_logging(level, settings.log_format)
    open_storage(settings).prepare()
    from pwlreg.service.celery_app import run_worker  # imports the worker and core: seconds

    _wait_for_schema(settings, SCHEMA_WAIT_SECONDS)
    return run_worker(settings, args.concurrency or settings.workers,
                      logging.getLevelName(level))


def _wait_for_schema(settings: Any, timeout: float) -> None:
    """Return once the job database answers at the schema revision of this release; raise
    :class:`CommandError` at once for a revision this release does not know, or after
    ``timeout`` seconds."""
    from pwlreg.service.store import JobStore, SchemaBehind, SchemaError

    store = JobStore.from_url(settings.resolved_database_url)
    deadline = time.monotonic() + timeout
    waiting = ""
    try:
        while True:
            try:
                store.check_schema()
                return
            except SchemaBehind as exc:
                reason = str(exc)
            except SchemaError as exc:
                raise CommandError(str(exc)) from None
            except Exception as exc:  # noqa: BLE001 (a database not up yet: wait for it)
                reason = f"job database unusable: {type(exc).__name__}: {exc}"
            if time.monotonic() > deadline:
                raise CommandError(f"{reason} (waited {timeout:g} s)")
            if reason != waiting:
                logging.getLogger("pwlreg.service.cli").warning("waiting: %s", reason)
                waiting = reason
            time.sleep(1.0)
    finally:
        store.dispose()  # the pool processes open their own connections


# --- parser ----------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pwlreg",
        description="Piecewise-linear image registration: locally, as a service, or as a client "
        "of the service.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    serve = sub.add_parser("serve", help="run the HTTP service",
                           description=cmd_serve.__doc__)
    serve.add_argument("--host", default="127.0.0.1", help="interface (default: 127.0.0.1)")
    serve.add_argument("--port", type=int, default=8000, help="port (default: 8000)")
    serve.add_argument("--data-dir", type=Path, default=None,
                       help="data directory (default: PWLREG_DATA_DIR or ./data)")
    serve.add_argument("--workers", type=int, default=None,
                       help="worker processes (default: PWLREG_WORKERS or the CPU count)")
    serve.add_argument("--log-level", default="info",
                       choices=["critical", "error", "warning", "info", "debug"])
    serve.set_defaults(func=cmd_serve)

    worker = sub.add_parser("worker", help="run a Celery worker (scale-out mode)",
                            description=cmd_worker.__doc__)
    worker.add_argument("--concurrency", type=int, default=None,
                        help="registrations at once, one process each (default: PWLREG_WORKERS "
                        "or the CPU count)")
    worker.add_argument("--data-dir", type=Path, default=None,
                        help="the data directory shared with the API (default: PWLREG_DATA_DIR "
                        "or ./data)")
    worker.add_argument("--log-level", default="info",
                        choices=["critical", "error", "warning", "info", "debug"])
    worker.set_defaults(func=cmd_worker)

    register = sub.add_parser("register", help="register an image pair in this process",
                              description=cmd_register.__doc__)
    register.add_argument("reference", help="reference image file")
    register.add_argument("moving", help="moving image file")
    register.add_argument("--out", required=True, type=Path,
                          help="output directory (mesh.json, registered.png, convergence.json)")
    register.add_argument("--points", help="conjugate points file (JSON or CSV pixel pairs, "
                          "a QGIS .points file, or a GeoTIFF with the moving image's GCPs), or "
                          "'gcps' for the moving GeoTIFF's own GCPs; default: automatic "
                          "matching")
    register.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    add_option_arguments(register)
    register.set_defaults(func=cmd_register)

    submit = sub.add_parser("submit", help="run a registration on a pwlreg service",
                            description=cmd_submit.__doc__)
    submit.add_argument("reference", help="reference image file")
    submit.add_argument("moving", help="moving image file")
    submit.add_argument("--out", required=True, help="output directory for the three results")
    submit.add_argument("--points", help="conjugate points file (JSON or CSV pixel pairs, a "
                        "QGIS .points file, or a GeoTIFF with the moving image's GCPs), or "
                        "'gcps' for the moving GeoTIFF's own GCPs")
    submit.add_argument("--url", default=os.environ.get("PWLREG_URL", DEFAULT_URL),
                        help=f"service URL (default: PWLREG_URL or {DEFAULT_URL})")
    submit.add_argument("--idempotency-key", help="send this Idempotency-Key (safe retries)")
    submit.add_argument("--api-key", default=os.environ.get("PWLREG_API_KEY"),
                        help="API key of a service that requires one (default: $PWLREG_API_KEY)")
    submit.add_argument("--poll-interval", type=float, default=0.5,
                        help="seconds between status polls (default: 0.5)")
    submit.add_argument("--timeout", type=float, default=3600.0,
                        help="give up waiting after this many seconds (default: 3600)")
    submit.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    add_option_arguments(submit)
    submit.set_defaults(func=cmd_submit)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``pwlreg`` command; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except CommandError as exc:
        print(f"pwlreg {args.command}: error: {exc}", file=sys.stderr)
        return exc.code


if __name__ == "__main__":
    sys.exit(main())
