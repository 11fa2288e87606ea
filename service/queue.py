"""The job queue: carries accepted jobs to workers.

The job rows are the truth: a job is queued because its row says ``accepted``, not because some
in-memory structure holds it. The queue only decides when a worker runs which job, so a queue
lost with its process loses no job; :meth:`JobQueue.start` rebuilds it from the store.

:class:`JobQueue` is the interface the API uses. :class:`LocalProcessQueue` runs the jobs in a
pool of local worker processes (the work is CPU-bound, embedded mode); :class:`CeleryQueue` hands
them to Celery workers through a broker (scale-out mode), which call the same
:func:`service.worker.run_job`.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from datetime import timedelta
from functools import partial

from pwlreg.service.logs import job_extra
from pwlreg.service.settings import Settings
from pwlreg.service.store import FINISHED, JobStatus, JobStore, utcnow
from pwlreg.service.worker import init_process, new_owner, ping, run_in_process

log = logging.getLogger(__name__)

THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""Environment variables that size the thread pools of numerical libraries."""


class JobQueue(ABC):
    """Where accepted jobs wait for a worker.

    Both implementations dispatch from a thread of the API process that a store poll or
    :meth:`enqueue` wakes; this holds what they share.
    """

    def __init__(
        self,
        settings: Settings,
        store: JobStore,
        on_finished: Callable[[str], None] | None = None,
        poll_interval: float = 1.0,
    ) -> None:
        self.settings = settings
        self.store = store
        self.on_finished = on_finished
        self.poll_interval = poll_interval
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._stopping = False

    @abstractmethod
    def start(self) -> None:
        """Start dispatching, including the jobs already accepted in the store."""

    @abstractmethod
    def stop(self, timeout: float = 10.0) -> None:
        """Stop dispatching; running jobs are given back to the queue (their rows go back to
        ``accepted``) or, if they do not stop within ``timeout`` seconds, killed (their leases
        expire and the next start requeues them)."""

    @abstractmethod
    def enqueue(self, job_id: str) -> None:
        """Tell the queue that the accepted job ``job_id`` is waiting."""

    @abstractmethod
    def is_ready(self) -> bool:
        """True if jobs will be dispatched (the workers and the broker are reachable)."""

    @abstractmethod
    def depth(self) -> int:
        """Number of jobs waiting for a worker."""


class LocalProcessQueue(JobQueue):
    """A pool of local worker processes fed from the job store, oldest job first.

    A dispatcher thread keeps at most ``settings.workers`` jobs in the pool, so that the pool
    holds no backlog of its own: the backlog is the accepted rows. It wakes up on
    :meth:`enqueue`, when a job ends, and every ``poll_interval`` seconds (jobs accepted by
    another process, jobs requeued by recovery).

    Parameters
    ----------
    settings : Settings
        ``workers`` is the pool size; the whole settings are passed to the workers.
    store : JobStore
    on_finished : callable, optional
        Called with the job id after each attempt ends (e.g. to record metrics).
    poll_interval : float
        Seconds between two looks at the store when nothing wakes the dispatcher.
    """

    def __init__(
        self,
        settings: Settings,
        store: JobStore,
        on_finished: Callable[[str], None] | None = None,
        poll_interval: float = 1.0,
    ) -> None:
        super().__init__(settings, store, on_finished, poll_interval)
        self._context = multiprocessing.get_context("spawn")
        self._stop_event = self._context.Event()
        self._lock = threading.Lock()
        # job id -> (future, lease owner, executor generation)
        self._inflight: dict[str, tuple[Future[str], str, int]] = {}
        self._executor: ProcessPoolExecutor | None = None
        self._generation = 0
        self._broken = False
        # Jobs that were running when a worker process died: any of them may be the one that
        # killed it, so each runs alone until it ends without breaking the pool, and an attempt
        # counts only when its job broke the pool alone (then only the culprit uses up its
        # attempts, not the jobs that shared the pool with it).
        self._suspects: set[str] = set()
        # generation of a broken pool -> the jobs that were running in it when it broke
        self._broken_batches: dict[int, set[str]] = {}

    # --- interface -----------------------------------------------------------------------------

    def start(self) -> None:
        self._executor = self._new_executor()
        self._thread = threading.Thread(target=self._run, name="job-dispatcher", daemon=True)
        self._thread.start()

    def enqueue(self, job_id: str) -> None:
        self._wake.set()

    def is_ready(self) -> bool:
        return (
            self._thread is not None
            and self._thread.is_alive()
            and self._executor is not None
            and not self._stopping
        )

    def depth(self) -> int:
        return self.store.count_by_status()[JobStatus.accepted]

    def stop(self, timeout: float = 10.0) -> None:
        self._stopping = True
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._stop_event.set()
        executor = self._executor
        if executor is None:
            return
        processes = list((getattr(executor, "_processes", None) or {}).values())
        # Running jobs see the stop event at their next progress report and give their job
        # back; queued calls are cancelled. Wait in a helper thread to bound the wait.
        closer = threading.Thread(
            target=executor.shutdown, kwargs={"wait": True, "cancel_futures": True}
        )
        closer.start()
        closer.join(timeout)
        if closer.is_alive():
            log.warning("workers did not stop within %.0f s; killing them", timeout)
            for process in processes:
                if process.is_alive():
                    process.kill()
            closer.join(5.0)
        self._executor = None

    # --- dispatcher ----------------------------------------------------------------------------

    def _new_executor(self) -> ProcessPoolExecutor:
        # The thread pools of numpy's BLAS and OpenMP are sized when the library loads, from
        # the environment the worker process inherits: set it before spawning. (An operator's
        # explicit setting wins.)
        threads = str(self.settings.worker_threads)
        for variable in THREAD_VARIABLES:
            os.environ.setdefault(variable, threads)
        executor = ProcessPoolExecutor(
            max_workers=self.settings.workers,
            mp_context=self._context,
            initializer=init_process,
            initargs=(self.settings, self._stop_event, logging.getLogger().getEffectiveLevel(),
                      True),
        )
        # Start the processes now (they import core), not when the first job arrives.
        for _ in range(self.settings.workers):
            executor.submit(ping)
        return executor

    def _run(self) -> None:
        while not self._stopping:
            try:
                if self._broken:
                    self._replace_executor()
                self._fill()
            except Exception:  # noqa: BLE001 (the dispatcher must survive a database hiccup)
                log.exception("dispatcher pass failed; retrying")
                time.sleep(self.poll_interval)
            self._wake.wait(self.poll_interval)
            self._wake.clear()

    def _fill(self) -> None:
        assert self._executor is not None
        with self._lock:
            free = self.settings.workers - len(self._inflight)
            busy = list(self._inflight)
            suspects = set(self._suspects)
        if free <= 0 or suspects.intersection(busy):
            return
        for job_id in self.store.next_accepted(free, exclude=busy):
            if self._stopping:
                return
            if job_id in suspects:
                if busy:
                    return  # it waits for the pool to empty; the jobs after it wait too
                free = 0  # it runs alone: nothing after it in this pass
            owner = new_owner()
            try:
                future = self._executor.submit(run_in_process, job_id, owner)
            except (BrokenProcessPool, RuntimeError):
                self._broken = True
                return
            with self._lock:
                self._inflight[job_id] = (future, owner, self._generation)
            busy.append(job_id)
            future.add_done_callback(partial(self._done, job_id))
            if free == 0:
                return

    def _done(self, job_id: str, future: Future[str]) -> None:
        exc = None if future.cancelled() else future.exception()
        broken = isinstance(exc, BrokenProcessPool)
        shared = False
        with self._lock:
            _, owner, generation = self._inflight.pop(job_id, (None, "", -1))
            if broken:
                self._suspects.add(job_id)
                # The first job to hear of the break sees the others still in flight.
                batch = self._broken_batches.setdefault(generation, {
                    other for other, (_, _, g) in self._inflight.items() if g == generation
                } | {job_id})
                shared = len(batch) > 1
            else:
                self._suspects.discard(job_id)
        if not future.cancelled():
            if broken:
                # A worker process died (killed, out of memory, a crash in a native library)
                # and the pool is replaced. A job that broke it alone is the culprit: its lease
                # expires and the maintenance pass requeues it, the attempt counted. Jobs that
                # shared the pool get their attempt back now; each then runs alone.
                log.error("worker pool broken while running job %s: %s", job_id, exc,
                          extra=job_extra(job_id))
                if shared and self.store.release(
                    job_id, owner, "requeued: a worker process died while it ran beside other "
                    "jobs; it runs alone next"
                ):
                    log.warning("job %s: attempt given back; it runs alone next", job_id,
                                extra=job_extra(job_id))
                self._broken = True
            elif exc is not None:
                log.error("job %s: worker raised %r", job_id, exc, extra=job_extra(job_id))
        if self.on_finished is not None:
            try:
                self.on_finished(job_id)
            except Exception:  # noqa: BLE001
                log.exception("on_finished callback failed for job %s", job_id,
                              extra=job_extra(job_id))
        self._wake.set()

    def _replace_executor(self) -> None:
        old = self._executor
        self._broken = False
        if old is not None:
            old.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            # The broken pool's futures call back one after the other, perhaps after this:
            # those still to call back stay, so that each finds the jobs it ran beside.
            self._inflight = {job_id: entry for job_id, entry in self._inflight.items()
                              if not entry[0].done()}
            self._generation += 1
            for generation in [g for g in self._broken_batches if g < self._generation - 1]:
                del self._broken_batches[generation]
        self._executor = self._new_executor()
        log.warning("worker pool replaced")


class CeleryQueue(JobQueue):
    """Accepted jobs handed to Celery workers through a broker (``pwlreg worker``).

    A dispatcher thread sends one message per accepted job that has none: new jobs, jobs given
    back by a stopping worker or requeued after a worker died (their rows go back to
    ``accepted`` undispatched), and jobs whose message was sent longer ago than the broker's
    visibility timeout (a broker restarted without its data loses its messages). It marks the
    row before it sends, so that several API processes send each job once; a message that
    cannot be sent is unmarked and sent at a later pass. It wakes on :meth:`enqueue` and every
    ``poll_interval`` seconds. A duplicate message is harmless: the worker's claim refuses a
    job that is not waiting.

    The same thread watches the jobs it dispatched (and, after a start, those still
    unfinished) and calls ``on_finished`` when one ends, as the local pool does.

    Parameters
    ----------
    settings : Settings
        ``broker_url`` and ``broker_queue`` name the broker and the queue.
    store : JobStore
    on_finished : callable, optional
        Called with the job id once a watched job has ended.
    poll_interval : float
        Seconds between two passes when nothing wakes the dispatcher.
    """

    def __init__(
        self,
        settings: Settings,
        store: JobStore,
        on_finished: Callable[[str], None] | None = None,
        poll_interval: float = 1.0,
    ) -> None:
        # Celery is an optional dependency (the extra 'scaleout'): imported in this mode only.
        from pwlreg.service.celery_app import TASK, make_celery, visibility_timeout

        super().__init__(settings, store, on_finished, poll_interval)
        self.app = make_celery(settings)
        self._task = TASK
        self._resend_after = timedelta(seconds=visibility_timeout(settings))
        self._watching: set[str] = set()
        self._broker_down = False

    def start(self) -> None:
        self._watching.update(self.store.unfinished_ids())
        self._thread = threading.Thread(target=self._run, name="job-dispatcher", daemon=True)
        self._thread.start()

    def enqueue(self, job_id: str) -> None:
        self._wake.set()

    def is_ready(self) -> bool:
        if self._thread is None or not self._thread.is_alive() or self._stopping:
            return False
        try:
            with self.app.connection_for_write() as connection:
                connection.ensure_connection(max_retries=1, interval_start=0, timeout=2.0)
        except Exception as exc:  # noqa: BLE001 (any broker failure means not ready)
            log.warning("broker unreachable: %s", exc)
            return False
        return True

    def depth(self) -> int:
        return self.store.count_by_status()[JobStatus.accepted]

    def stop(self, timeout: float = 10.0) -> None:
        self._stopping = True
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self.app.close()

    def _run(self) -> None:
        while not self._stopping:
            try:
                self._dispatch()
                self._watch()
            except Exception:  # noqa: BLE001 (the dispatcher must survive a hiccup)
                log.exception("dispatcher pass failed; retrying")
            self._wake.wait(self.poll_interval)
            self._wake.clear()

    def _dispatch(self) -> None:
        while not self._stopping:
            sent_before = utcnow() - self._resend_after
            batch = self.store.undispatched(100, sent_before)
            for job_id in batch:
                if not self.store.mark_dispatched(job_id, sent_before):
                    continue  # dispatched by another API process, or no longer accepted
                try:
                    self.app.send_task(self._task, args=[job_id],
                                       queue=self.settings.broker_queue)
                except Exception as exc:  # noqa: BLE001 (sent again at the next pass)
                    self.store.unmark_dispatched(job_id)
                    if not self._broker_down:
                        log.warning("job %s: not sent to the broker (%s); retrying every "
                                    "%g s", job_id, exc, self.poll_interval,
                                    extra=job_extra(job_id))
                    self._broker_down = True
                    return
                if self._broker_down:
                    log.warning("broker reachable again; sending the waiting jobs")
                    self._broker_down = False
                self._watching.add(job_id)
            if len(batch) < 100:
                return

    def _watch(self) -> None:
        if not self._watching:
            return
        statuses = self.store.statuses(list(self._watching))
        for job_id in list(self._watching):
            status = statuses.get(job_id)
            if status is not None and status not in FINISHED:
                continue
            self._watching.discard(job_id)
            if status is not None and self.on_finished is not None:
                try:
                    self.on_finished(job_id)
                except Exception:  # noqa: BLE001
                    log.exception("on_finished callback failed for job %s", job_id,
                                  extra=job_extra(job_id))
