"""Artifact storage: the uploaded inputs and the results of every job.

:class:`Storage` is what the API, the workers and the maintenance pass use; :class:`LocalStorage`
keeps the files in a directory, which in scale-out mode is a volume shared by the API and every
worker (nothing of a job lives only on one worker's disk). An object store can implement the same
interface: its paths are then those of a local cache (inputs fetched before a worker reads them,
results uploaded by :meth:`Storage.publish_results` and fetched when served).

Layout under the data directory::

    uploads/<random>/            a request being received (moved away or removed when done)
    jobs/<id>/inputs/            reference, moving, points (as uploaded)
    jobs/<id>/work-<owner>/      results being written by one attempt
    jobs/<id>/results/           the result files (core.results.RESULTS; complete or absent)

Every visible state is reached by a rename, so a reader never sees half a job or half a result.
"""

from __future__ import annotations

import os
import shutil
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from pathlib import Path

from pwlreg.core.results import RESULTS
from pwlreg.service.settings import Settings

IMAGES = ("reference", "moving")
"""Names of the images of a job, stored as uploaded: the API only checks their headers and
structure, the worker decodes them (decoding is CPU work, and the worker pool is what scales)."""


class Storage(ABC):
    """Where the files of the jobs are kept.

    Paths returned are local files: a reader never sees half a job or half a result, and a
    result path is either complete or absent.
    """

    @abstractmethod
    def prepare(self) -> None:
        """Make the storage usable; raise OSError if it is not writable."""

    @abstractmethod
    def is_writable(self) -> bool:
        """True if new files can be stored."""

    @abstractmethod
    def new_staging(self) -> Path:
        """A new empty local directory for the files of one request."""

    @abstractmethod
    def commit_inputs(self, staging: Path, job_id: str) -> None:
        """Make a staging directory the inputs of ``job_id``, durably, before the job row is
        inserted."""

    @abstractmethod
    def discard(self, path: Path) -> None:
        """Remove a staging directory, ignoring a missing one."""

    @abstractmethod
    def image_path(self, job_id: str, name: str) -> Path:
        """Local path of the image ``name`` (one of :data:`IMAGES`) of ``job_id``."""

    @abstractmethod
    def points_path(self, job_id: str) -> Path:
        """Local path of the points file of ``job_id``."""

    @abstractmethod
    def work_dir(self, job_id: str, owner: str) -> Path:
        """A fresh local directory for the results of one attempt."""

    @abstractmethod
    def publish_results(self, job_id: str, work_dir: Path) -> bool:
        """Make the results of ``work_dir`` visible at once; False if another attempt
        published first or the job's files were removed."""

    @abstractmethod
    def discard_attempts(self, job_id: str, owner: str | None = None) -> None:
        """Remove the work directories of attempts of ``job_id`` that did not publish: every
        one, or only that of ``owner``'s attempt."""

    @abstractmethod
    def result_path(self, job_id: str, name: str) -> Path | None:
        """Local path of the result ``name`` (a key of :data:`RESULTS`), or None if absent."""

    @abstractmethod
    def result_names(self, job_id: str) -> list[str]:
        """Names of the results stored for a job, in the order of :data:`RESULTS`."""

    @abstractmethod
    def remove(self, job_id: str) -> None:
        """Remove every file of ``job_id``."""

    @abstractmethod
    def sweep(self, is_known: Callable[[Iterable[str]], set[str]], older_than: float) -> int:
        """Remove leftovers older than ``older_than`` seconds (interrupted uploads, files of
        jobs without a row); returns how many were removed."""


def open_storage(settings: Settings) -> Storage:
    """The storage the settings name: the job files under ``settings.data_dir``."""
    return LocalStorage(settings.data_dir)


class LocalStorage(Storage):
    """Job files under one root directory (a local disk or a volume shared by every process).

    Parameters
    ----------
    root : pathlib.Path
        The data directory; ``uploads/`` and ``jobs/`` are created under it.
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.uploads = self.root / "uploads"
        self.jobs = self.root / "jobs"

    def prepare(self) -> None:
        """Create the directories; raise OSError if the data directory is not writable."""
        self.uploads.mkdir(parents=True, exist_ok=True)
        self.jobs.mkdir(parents=True, exist_ok=True)

    def is_writable(self) -> bool:
        """True if the data directory exists and accepts new files."""
        return os.access(self.jobs, os.W_OK | os.X_OK) and os.access(self.uploads, os.W_OK)

    # --- uploads -----------------------------------------------------------------------------

    def new_staging(self) -> Path:
        """A new empty directory for the files of one request."""
        path = self.uploads / uuid.uuid4().hex
        path.mkdir(parents=True)
        return path

    def commit_inputs(self, staging: Path, job_id: str) -> None:
        """Move a staging directory to the inputs of ``job_id`` (atomic rename), synced to disk
        so that the inputs of an accepted job survive a power cut."""
        for path in staging.iterdir():
            _fsync(path)
        job_dir = self.jobs / job_id
        job_dir.mkdir(parents=True, exist_ok=True)
        os.replace(staging, job_dir / "inputs")
        _fsync(job_dir)
        _fsync(self.jobs)

    @staticmethod
    def discard(path: Path) -> None:
        """Remove a staging directory, ignoring a missing one."""
        shutil.rmtree(path, ignore_errors=True)

    def image_path(self, job_id: str, name: str) -> Path:
        """Path of the image ``name`` (one of :data:`IMAGES`) of ``job_id``, as uploaded."""
        if name not in IMAGES:
            raise ValueError(f"unknown image {name!r}")
        return self.jobs / job_id / "inputs" / name

    def points_path(self, job_id: str) -> Path:
        """Path of the points file of ``job_id``, as uploaded."""
        return self.jobs / job_id / "inputs" / "points"

    # --- results -----------------------------------------------------------------------------

    def _work_path(self, job_id: str, owner: str) -> Path:
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in owner)
        return self.jobs / job_id / f"work-{safe}"

    def work_dir(self, job_id: str, owner: str) -> Path:
        """A fresh directory for the results of one attempt."""
        path = self._work_path(job_id, owner)
        shutil.rmtree(path, ignore_errors=True)
        path.mkdir(parents=True)
        return path

    def publish_results(self, job_id: str, work_dir: Path) -> bool:
        """Make the results of ``work_dir`` visible (atomic rename); False if another attempt
        published first or the job's files were removed."""
        target = self.jobs / job_id / "results"
        if target.exists() or not work_dir.is_dir():
            shutil.rmtree(work_dir, ignore_errors=True)
            return False
        try:
            os.replace(work_dir, target)
        except OSError:
            shutil.rmtree(work_dir, ignore_errors=True)
            return False
        return True

    def discard_attempts(self, job_id: str, owner: str | None = None) -> None:
        if owner is not None:
            shutil.rmtree(self._work_path(job_id, owner), ignore_errors=True)
            return
        for path in (self.jobs / job_id).glob("work-*"):
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)

    def result_path(self, job_id: str, name: str) -> Path | None:
        """Path of the result ``name`` (a key of :data:`RESULTS`), or None if absent."""
        path = self.jobs / job_id / "results" / RESULTS[name].filename
        return path if path.is_file() else None

    def result_names(self, job_id: str) -> list[str]:
        """Names of the results stored for a job, in the order of :data:`RESULTS`."""
        folder = self.jobs / job_id / "results"
        return [name for name, fmt in RESULTS.items() if (folder / fmt.filename).is_file()]

    # --- removal -----------------------------------------------------------------------------

    def remove(self, job_id: str) -> None:
        """Remove every file of ``job_id`` (inputs, results, attempts in progress)."""
        shutil.rmtree(self.jobs / job_id, ignore_errors=True)

    def sweep(self, is_known: Callable[[Iterable[str]], set[str]], older_than: float) -> int:
        """Remove leftovers older than ``older_than`` seconds: staging directories of requests
        that never finished, and job directories without a job row (crash between the file move
        and the insert, or a deleted row). Returns the number of directories removed."""
        limit = time.time() - older_than
        removed = 0
        for path in list(self.uploads.iterdir()) if self.uploads.is_dir() else []:
            if _mtime(path) < limit:
                shutil.rmtree(path, ignore_errors=True)
                removed += 1
        candidates = [
            p for p in (self.jobs.iterdir() if self.jobs.is_dir() else []) if _mtime(p) < limit
        ]
        known = is_known([p.name for p in candidates])
        for path in candidates:
            if path.name not in known:
                shutil.rmtree(path, ignore_errors=True)
                removed += 1
        return removed


def _fsync(path: Path) -> None:
    """Flush a file or a directory entry to disk (directories: POSIX only)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # directories cannot be synced on some platforms
    finally:
        os.close(fd)


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return float("inf")
