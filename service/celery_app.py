"""The Celery side of the scale-out mode: the broker configuration, the one task, the worker.

The broker carries only job ids; the job row stays the truth. A message is acknowledged after
its task returned (late acknowledgement), so a worker that dies, whole or one of its pool
processes, leaves its message to be delivered again; the database lease and attempt counter
decide whether a delivery runs (:meth:`~pwlreg.service.store.JobStore.claim`): a job completes
once, and a job whose workers keep dying fails after ``max_attempts``. The API process sends the
messages (:class:`~pwlreg.service.queue.CeleryQueue`); ``pwlreg worker`` runs :func:`run_worker`.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import socket
from typing import Any

from celery import Celery
from celery.signals import worker_process_init, worker_shutting_down

from pwlreg.service.settings import Settings
from pwlreg.service.worker import init_process, run_in_process

TASK = "pwlreg.run_job"
"""Name of the task: run the job whose id is its one argument."""


def visibility_timeout(settings: Settings) -> float:
    """Seconds a delivered, unacknowledged message waits before a Redis broker delivers it
    again: longer than an attempt may last (the time limit, then one lease until the heartbeat
    ends a stuck registration), so that a job still running is never delivered twice."""
    return settings.job_time_limit + 2 * settings.lease_seconds + 60.0


def make_celery(settings: Settings) -> Celery:
    """A Celery application for ``settings.broker_url`` (Redis or RabbitMQ, by URL alone).

    No result backend: the results are in the job rows and the storage.
    """
    app = Celery("pwlreg", broker=settings.broker_url, set_as_current=False)
    app.conf.update(
        task_default_queue=settings.broker_queue,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_ignore_result=True,
        task_serializer="json",
        accept_content=["json"],
        # One message per pool process at a time: a busy worker holds no backlog that an idle
        # one could run, and a dead worker held only the jobs it was running.
        worker_prefetch_multiplier=1,
        worker_hijack_root_logger=False,  # the service's own logging (PWLREG_LOG_FORMAT)
        worker_redirect_stdouts=False,
        broker_connection_retry_on_startup=True,
        broker_connection_timeout=5.0,
        # The API's dispatcher retries a message that could not be sent: fail fast instead.
        task_publish_retry_policy={"max_retries": 2, "interval_start": 0,
                                   "interval_step": 0.5, "interval_max": 1},
        broker_transport_options={"visibility_timeout": visibility_timeout(settings),
                                  "socket_timeout": 30.0},
    )
    return app


def run_worker(settings: Settings, concurrency: int, log_level: int = logging.INFO) -> int:
    """Run a Celery worker of ``concurrency`` pool processes until it is stopped; returns its
    exit code.

    Each pool process builds its worker context (store, storage, runner, numba kernels) once,
    as the embedded pool does. On SIGTERM or Ctrl-C the running registrations stop at their next
    progress report and their jobs go back to ``accepted`` without using an attempt (the API
    sends them again); SIGQUIT or a second Ctrl-C stops at once (the leases expire, the jobs are
    run again).
    """
    app = make_celery(settings)
    # Created before the pool forks its processes, which inherit it.
    stop_event = multiprocessing.get_context("fork").Event()

    @app.task(name=TASK)
    def run_job(job_id: str) -> str:
        return run_in_process(job_id)

    def init(**_: Any) -> None:
        init_process(settings, stop_event, log_level)

    def stopping(**_: Any) -> None:
        stop_event.set()

    worker_process_init.connect(init, weak=False)
    worker_shutting_down.connect(stopping, weak=False)
    worker = app.Worker(
        hostname=f"pwlreg-{os.getpid()}@{socket.gethostname()}",
        concurrency=concurrency,
        pool="prefork",
        queues=[settings.broker_queue],
        loglevel=log_level,
        without_mingle=True,
        without_gossip=True,
        without_heartbeat=True,
    )
    worker.start()
    return worker.exitcode or 0
