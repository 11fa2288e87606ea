"""The worker: runs one job in a worker process, from its stored inputs to its stored results.

The same code runs in the processes of the embedded pool (:mod:`service.queue`) and of a Celery
worker (:mod:`service.celery_app`). :func:`run_job` claims the job (accepted -> running, under a
lease), loads the inputs, calls the registration function (``core.pipeline.register`` unless the
settings name another) and stores the results. While it runs, a heartbeat thread writes the
stage and progress to the job row, renews the lease and notices a dismissal; the progress
callback passed to the registration raises when the job was dismissed, ran past its time limit
or the service is shutting down, which stops the registration at its next progress report.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import signal
import socket
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np
from pydantic import ValidationError

from pwlreg.core import kernels
from pwlreg.core.errors import InputError, NotEnoughPointsError, UnreliableResultError
from pwlreg.core.formats.geotiff import RasterFile, open_image
from pwlreg.core.io import load_points
from pwlreg.core.options import RegistrationOptions
from pwlreg.core.quality import refused
from pwlreg.core.results import Sources, write_outputs
from pwlreg.service.logs import configure_logging, job_extra
from pwlreg.service.problems import problem_document
from pwlreg.service.settings import Settings
from pwlreg.service.storage import IMAGES, Storage, open_storage
from pwlreg.service.store import JobStatus, JobStore

log = logging.getLogger(__name__)

STAGES: dict[str, tuple[float, float]] = {
    "matching": (0.0, 20.0),
    "triangulating": (20.0, 25.0),
    "optimizing": (25.0, 90.0),
    "rendering": (90.0, 99.0),
}
"""Stage -> (start, end) of the overall progress in percent."""

STAGE_TIMINGS: dict[str, tuple[str, ...]] = {
    "matching": ("matching_s",),
    "triangulating": ("triangulation_s",),
    "optimizing": ("optimization_s",),
    "rendering": ("rendering_s", "quality_s"),
}
"""Stage -> the keys of the registration's ``timings`` it spans (the quality assessment runs
within the 'rendering' stage of the progress)."""


def stage_timings(timings: Mapping[str, float] | None) -> dict[str, float] | None:
    """Seconds per stage (:data:`STAGE_TIMINGS`) from a registration's ``timings``, for the
    job row; None if it has none."""
    if not timings:
        return None
    stages = {}
    for stage, keys in STAGE_TIMINGS.items():
        values = [float(timings[k]) for k in keys if isinstance(timings.get(k), int | float)]
        if values:
            stages[stage] = sum(values)
    return stages or None


class Runner(Protocol):
    """The registration function (``core.pipeline.register``'s signature)."""

    def __call__(
        self,
        reference: Any,
        moving: Any,
        points: Any = None,
        options: RegistrationOptions | None = None,
        progress: Callable[[str, float], None] | None = None,
    ) -> Any: ...


class JobInterrupted(BaseException):
    """Raised from the progress callback to stop a registration.

    A ``BaseException`` (like ``asyncio.CancelledError``), so that an ``except Exception`` in
    the registration code cannot swallow it.
    """


class JobDismissed(JobInterrupted):
    """The client dismissed (cancelled) the job."""


class LeaseLost(JobInterrupted):
    """The job is no longer ours: its lease expired and another attempt took it over."""


class WorkerStopping(JobInterrupted):
    """The service is shutting down; the job goes back to the queue."""


class TimeLimitExceeded(JobInterrupted):
    """The attempt ran longer than the job time limit."""


def resolve_runner(path: str) -> Runner:
    """Import a ``module:function`` path (``core.pipeline:register``)."""
    module_name, _, attr = path.partition(":")
    if not module_name or not attr:
        raise ValueError(f"runner must be 'module:function', got {path!r}")
    return getattr(importlib.import_module(module_name), attr)


@dataclass
class WorkerContext:
    """What a worker needs, built once per worker process.

    Parameters
    ----------
    settings : Settings
    store : JobStore
    storage : Storage
    runner : callable, optional
        The registration function; None means "import ``settings.runner`` on first use".
    stop_event : threading.Event-like, optional
        Set by the service when it shuts down.
    abort : callable
        Ends the worker process when a registration is stuck past its time limit.
    """

    settings: Settings
    store: JobStore
    storage: Storage
    runner: Runner | None = None
    stop_event: Any = None
    abort: Callable[[], None] = field(default=lambda: os._exit(70))

    @classmethod
    def from_settings(
        cls, settings: Settings, runner: Runner | None = None, stop_event: Any = None
    ) -> WorkerContext:
        return cls(
            settings=settings,
            store=JobStore.from_url(settings.resolved_database_url),
            storage=open_storage(settings),
            runner=runner,
            stop_event=stop_event,
        )

    def get_runner(self) -> Runner:
        if self.runner is None:
            self.runner = resolve_runner(self.settings.runner)
        return self.runner


class ProgressReporter:
    """The progress callback of one attempt, and the heartbeat that keeps its lease.

    Calling the reporter (``reporter(stage, fraction)``, from the registration) only records the
    progress in memory and raises a :class:`JobInterrupted` when the attempt must stop: the
    service is shutting down, the time limit is over, or the heartbeat found the job dismissed
    or taken over. The registration stops at its next progress report.

    The heartbeat (:meth:`beat`, every ``progress_interval`` seconds from a thread started by
    :meth:`running`) writes the progress, renews the lease and reads back whether the job is
    still ours. It runs apart from the progress reports so that the lease measures whether the
    worker process is alive, not how often a stage reports: a long stage that reports rarely
    keeps its lease, a dead process loses it.

    Parameters
    ----------
    context : WorkerContext
    job_id, owner : str
        The job and the lease owner of this attempt.
    clock : callable
        Monotonic clock in seconds.
    """

    def __init__(
        self,
        context: WorkerContext,
        job_id: str,
        owner: str,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.context = context
        self.job_id = job_id
        self.owner = owner
        self.clock = clock
        self.started = clock()
        self.stage: str | None = None
        self.percent = 0.0
        self.interruption: JobInterrupted | None = None
        self._lock = threading.Lock()

    # --- the progress callback (registration thread) ---------------------------------------

    def __call__(self, stage: str, fraction: float) -> None:
        self.check()
        if stage in STAGES:
            start, end = STAGES[stage]
            f = min(max(float(fraction), 0.0), 1.0) if fraction == fraction else 0.0
            with self._lock:
                self.stage = stage
                self.percent = max(self.percent, start + f * (end - start))

    def check(self) -> None:
        """Raise the pending interruption, if any."""
        if self.interruption is not None:
            raise self.interruption
        stop = self.context.stop_event
        if stop is not None and stop.is_set():
            raise WorkerStopping("the service is shutting down")
        limit = self.context.settings.job_time_limit
        if self.clock() - self.started > limit:
            raise TimeLimitExceeded(f"the job ran longer than the time limit of {limit:g} s")

    # --- the heartbeat (heartbeat thread, and once more before publishing) --------------------

    def beat(self) -> None:
        """Write the progress and renew the lease; raise :class:`JobDismissed` or
        :class:`LeaseLost` if the job is no longer ours."""
        with self._lock:
            stage, percent = self.stage, round(self.percent, 1)
        store = self.context.store
        if store.renew(
            self.job_id, self.owner, self.context.settings.lease_seconds, stage, percent
        ):
            return
        job = store.get(self.job_id)
        if job is None or job.status == JobStatus.dismissed:
            raise JobDismissed("the job was dismissed")
        raise LeaseLost("the job's lease expired and another attempt took it over")

    @contextmanager
    def running(self) -> Iterator[None]:
        """Run the heartbeat in a thread while the block runs."""
        done = threading.Event()
        thread = threading.Thread(
            target=self._heartbeat, args=(done,), name=f"heartbeat-{self.job_id}", daemon=True
        )
        thread.start()
        try:
            yield
        finally:
            done.set()
            thread.join()

    def _heartbeat(self, done: threading.Event) -> None:
        settings = self.context.settings
        # A registration stuck without progress reports past the time limit (plus one lease)
        # cannot be stopped from inside: fail the job and end the worker process.
        hard_limit = settings.job_time_limit + settings.lease_seconds
        while not done.wait(settings.progress_interval):
            try:
                self.beat()
            except JobInterrupted as exc:
                self.interruption = exc
                return
            except Exception:  # noqa: BLE001 (a database hiccup: try again next beat)
                log.exception("job %s: heartbeat failed", self.job_id,
                              extra=job_extra(self.job_id))
            if self.clock() - self.started > hard_limit:
                detail = (
                    f"the job ran longer than the time limit of {settings.job_time_limit:g} s "
                    "and did not stop; its worker process was ended"
                )
                self.context.store.finish(
                    self.job_id, self.owner, JobStatus.failed, detail,
                    problem_document("time-limit-exceeded", "Time limit exceeded", 500, detail),
                )
                log.error("job %s: %s", self.job_id, detail, extra=job_extra(self.job_id))
                self.context.abort()
                return


def new_owner() -> str:
    """A lease owner: host, process and a random tag."""
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


def run_job(job_id: str, context: WorkerContext, owner: str | None = None) -> str:
    """Run one job to its end and return its final status (or ``"skipped"``).

    A job that cannot be claimed (dismissed meanwhile, finished, or running under another
    worker's live lease) is skipped. Errors about the input end the job as failed with a
    readable message; nothing raised by the registration escapes this function.
    """
    store, storage, settings = context.store, context.storage, context.settings
    owner = owner or new_owner()
    job = store.claim(job_id, owner, settings.lease_seconds)
    if job is None:
        return "skipped"
    jlog = logging.LoggerAdapter(log, job_extra(job_id, job.owner))
    jlog.info("job %s: attempt %d started by %s", job_id, job.attempts, owner)
    reporter = ProgressReporter(context, job_id, owner)
    lost = False  # the job turned out to be no longer ours (taken over, or dismissed)

    def settle_lost() -> str:
        nonlocal lost
        lost = True
        return _settle_lost(job_id, context)

    def dismissed() -> str:
        storage.remove(job_id)
        jlog.info("job %s: stopped, dismissed by the client", job_id)
        return JobStatus.dismissed.value

    def fail(error: dict[str, Any], quality: dict[str, Any] | None = None) -> str:
        if store.finish(job_id, owner, JobStatus.failed, error["detail"], error, quality):
            jlog.info("job %s: failed: %s", job_id, error["detail"])
            return JobStatus.failed.value
        return settle_lost()

    try:
        with reporter.running():
            with contextlib.ExitStack() as files:
                reference, moving = _read_images(context, job_id, files)
                points = None
                if job.has_points:
                    points = load_points(storage.points_path(job_id).read_bytes(),
                                         field="points")
                options = RegistrationOptions.model_validate(job.options)
                runner = context.get_runner()
                result = runner(reference, moving, points=points, options=options,
                                progress=reporter)
            reporter.check()
            work = storage.work_dir(job_id, owner)
            pictures = (i if isinstance(i, np.ndarray) else None for i in (reference, moving))
            sources = Sources(*pictures, storage.image_path(job_id, "reference"),
                              storage.image_path(job_id, "moving"), settings.worker_threads)
            write_outputs(result, work, sources=sources)
        reporter.beat()  # still ours (not dismissed) before the results become visible?
        storage.publish_results(job_id, work)
        summary = result.summary()
        if store.finish(
            job_id, owner, JobStatus.successful, summary, quality=result.quality.to_dict(),
            timings=stage_timings(getattr(result, "timings", None)),
        ):
            jlog.info("job %s: successful: %s", job_id, summary)
            return JobStatus.successful.value
        return settle_lost()
    except JobDismissed:
        return dismissed()
    except LeaseLost:
        lost = True
        jlog.warning("job %s: lease lost, attempt by %s abandoned", job_id, owner)
        return "skipped"
    except WorkerStopping:
        lost = not store.release(job_id, owner,
                                 "requeued: the service was shut down while the job ran")
        jlog.info("job %s: released for the next start", job_id)
        return JobStatus.accepted.value
    except TimeLimitExceeded as exc:
        return fail(problem_document("time-limit-exceeded", "Time limit exceeded", 500, str(exc)))
    except UnreliableResultError as exc:
        return fail(
            problem_document("unreliable-result", "Registration unreliable", 422, str(exc)),
            exc.quality,
        )
    except InputError as exc:
        field = getattr(exc, "field", None)
        detail = f"{field}: {exc}" if field else str(exc)
        # Too few reliable pairs is a verdict on the images too: unreliable, and why.
        quality = refused(str(exc), exc.found) if isinstance(exc, NotEnoughPointsError) else None
        return fail(
            problem_document("registration-failed", "Input cannot be registered", 422, detail,
                             field),
            quality,
        )
    except ValidationError as exc:
        return fail(
            problem_document("registration-failed", "Invalid options", 422, str(exc), "options")
        )
    except Exception as exc:  # noqa: BLE001 (a bug must fail the job, not the worker)
        now = store.get(job_id)
        if now is None or now.status == JobStatus.dismissed:
            # Dismissed while it ran: its files were removed under it, which raised here.
            return dismissed()
        jlog.error("job %s: internal error\n%s", job_id, traceback.format_exc())
        return fail(
            problem_document("internal-error", "Internal error", 500,
                f"internal error while registering: {type(exc).__name__}: {exc}",
            )
        )
    finally:
        # Attempts that did not publish leave nothing behind. One whose job was taken over
        # (its lease expired while it stalled) removes only its own: the attempt that took
        # the job over may be writing its results in its work directory right now.
        storage.discard_attempts(job_id, owner if lost else None)


def _read_images(context: WorkerContext, job_id: str, files: contextlib.ExitStack
                 ) -> list[np.ndarray | RasterFile]:
    """Decode the reference and the moving image of ``job_id`` (both at once if the worker has
    more than one thread; OpenCV's decoders release the GIL), or open them for reading window
    by window when they are large TIFFs (closed with ``files``). The API checked their headers
    and structure; a file that still fails to decode raises :class:`InputError` naming it."""
    settings = context.settings

    def read(name: str) -> np.ndarray | RasterFile:
        path = context.storage.image_path(job_id, name)
        # Jobs accepted before 2026-11-22 kept their inputs decoded, as <name>.npy.
        legacy = path.with_name(f"{name}.npy")
        if not path.exists() and legacy.exists():
            return np.load(legacy, allow_pickle=False)
        return open_image(path, max_pixels=settings.max_pixels,
                          max_raster_pixels=settings.max_raster_pixels, field=name,
                          threads=settings.worker_threads)

    if settings.worker_threads < 2:
        images = [read(name) for name in IMAGES]
    else:
        with ThreadPoolExecutor(len(IMAGES)) as pool:
            images = list(pool.map(read, IMAGES))
    for image in images:
        if isinstance(image, RasterFile):
            files.enter_context(image)
    return images


def _settle_lost(job_id: str, context: WorkerContext) -> str:
    """The final write found the job not ours any more: remove files of a dismissed job."""
    job = context.store.get(job_id)
    if job is None or job.status == JobStatus.dismissed:
        context.storage.remove(job_id)
        return JobStatus.dismissed.value
    return "skipped"


# --- glue for a pool of worker processes (local pool or Celery's) ---------------------------

_PROCESS_CONTEXT: WorkerContext | None = None


def init_process(
    settings: Settings, stop_event: Any = None, log_level: int = logging.INFO,
    ignore_terminate: bool = False,
) -> None:
    """Initializer of a worker process: build its context, follow the parent's lifetime.

    Ctrl-C in a terminal reaches the whole process group; the workers ignore it and let the
    service stop them through ``stop_event``. With ``ignore_terminate`` they ignore SIGTERM too
    (the embedded pool): systemd's default stop (``KillMode=control-group``) and ``kill -TERM
    -PGID`` signal the whole group, and a worker that died there cost its job an attempt. A
    worker exits when its parent process dies, so that a killed service leaves no orphan
    running jobs (their leases expire and the next start requeues them).
    """
    global _PROCESS_CONTEXT
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if ignore_terminate:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    cv2.setNumThreads(settings.worker_threads)  # processes, not threads, share the cores
    kernels.set_threads(settings.worker_threads)
    configure_logging(log_level, settings.log_format)
    _PROCESS_CONTEXT = WorkerContext.from_settings(settings, stop_event=stop_event)
    try:
        _PROCESS_CONTEXT.get_runner()  # import core once, before the first job
        if settings.runner in ("pwlreg.core.scaled:register", "pwlreg.core.pipeline:register"):
            from pwlreg.core.pipeline import warm_up

            warm_up()  # compile or load the numba kernels now, not in the first job
    except Exception:  # noqa: BLE001 (reported when a job runs)
        log.exception("cannot import the runner %s", settings.runner)
    _watch_parent()


def _watch_parent() -> None:
    import multiprocessing

    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        parent.join()
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def run_in_process(job_id: str, owner: str | None = None) -> str:
    """Entry point of the pool: :func:`run_job` with this process's context (``owner`` names
    the lease, so that the dispatcher can give the job back if the process dies)."""
    if _PROCESS_CONTEXT is None:
        raise RuntimeError("worker process not initialised (init_process)")
    return run_job(job_id, _PROCESS_CONTEXT, owner)


def ping() -> int:
    """A no-op task that makes the pool start its processes ahead of the first job."""
    return os.getpid()
