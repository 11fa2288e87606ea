"""Periodic maintenance: requeue jobs whose worker died, delete expired jobs and leftovers.

Kept apart from the queue, and run by the API process in both modes: with Celery workers too,
a job whose worker died goes back to ``accepted`` here and the queue sends it again.
"""

from __future__ import annotations

import logging
import threading
import time
from datetime import timedelta

from pwlreg.service.logs import job_extra
from pwlreg.service.problems import problem_document
from pwlreg.service.queue import JobQueue
from pwlreg.service.settings import Settings
from pwlreg.service.storage import Storage
from pwlreg.service.store import JobStore, utcnow

log = logging.getLogger(__name__)


def _attempts_exhausted(message: str) -> dict:
    return problem_document("attempts-exhausted", "Job attempts exhausted", 500, message)

LEFTOVER_AGE_SECONDS = 3600.0
"""Staging directories and job directories without a row are removed after this long."""


class Janitor:
    """Recovers expired leases every ``lease_seconds / 2`` and applies the retention every
    ``maintenance_interval`` seconds, in a background thread.

    Parameters
    ----------
    settings : Settings
    store : JobStore
    storage : Storage
    queue : JobQueue
        Told about the jobs it puts back to ``accepted``.
    """

    def __init__(
        self, settings: Settings, store: JobStore, storage: Storage, queue: JobQueue
    ) -> None:
        self.settings = settings
        self.store = store
        self.storage = storage
        self.queue = queue
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def recover(self) -> tuple[list[str], list[str]]:
        """Requeue the running jobs whose lease expired (fail those out of attempts)."""
        requeued, failed = self.store.recover_expired(_attempts_exhausted)
        for job_id in requeued:
            log.warning("job %s: lease expired (worker died); requeued", job_id,
                        extra=job_extra(job_id))
            self.queue.enqueue(job_id)
        for job_id in failed:
            log.error("job %s: lease expired and no attempts left; failed", job_id,
                      extra=job_extra(job_id))
        return requeued, failed

    def apply_retention(self) -> int:
        """Delete finished jobs older than the retention, with their files; returns how many."""
        cutoff = utcnow() - timedelta(seconds=self.settings.retention)
        deleted = 0
        while True:
            ids = self.store.expired_finished(cutoff)
            if not ids:
                break
            for job_id in ids:
                self.storage.remove(job_id)
            deleted += self.store.delete(ids)
        self.storage.sweep(self.store.existing_ids, LEFTOVER_AGE_SECONDS)
        if deleted:
            log.info("retention: deleted %d expired jobs", deleted)
        return deleted

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="janitor", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        lease_every = self.settings.lease_seconds / 2
        next_retention = 0.0
        while not self._stop.is_set():
            try:
                self.recover()
                now = time.monotonic()
                if now >= next_retention:
                    self.apply_retention()
                    next_retention = now + self.settings.maintenance_interval
            except Exception:  # noqa: BLE001 (keep maintaining after a database hiccup)
                log.exception("maintenance pass failed")
            self._stop.wait(min(lease_every, self.settings.maintenance_interval))
