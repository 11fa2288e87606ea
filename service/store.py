"""The job store: one SQLAlchemy table, the source of truth of every job.

A job row holds the status, the progress, the attempts and the lease of the worker running it.
Every transition is a single conditional ``UPDATE`` (``... WHERE status = 'accepted'``), so that
several processes (the API, the workers, other machines) never step on each other: the first
writer wins and the others see ``rowcount == 0``.

The same code runs on SQLite (embedded mode) and PostgreSQL (scale-out); the schema is created
and upgraded by the Alembic revisions of :mod:`pwlreg.service.migrations`.
"""

from __future__ import annotations

import enum
import uuid
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from alembic.util import CommandError
from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    Index,
    Integer,
    String,
    Text,
    and_,
    create_engine,
    event,
    func,
    or_,
    select,
    text,
    update,
)
from sqlalchemy.engine import Engine
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker
from sqlalchemy.types import TypeDecorator

MIGRATIONS = Path(__file__).with_name("migrations")
"""The Alembic environment and revisions of the job table."""

SCHEMA_LOCK = 0x70776C72
"""Key of the PostgreSQL advisory lock that serializes the schema upgrades of API processes
starting together (replicas)."""


class JobStatus(enum.StrEnum):
    """Status words of OGC API - Processes."""

    accepted = "accepted"
    running = "running"
    successful = "successful"
    failed = "failed"
    dismissed = "dismissed"


FINISHED = (JobStatus.successful, JobStatus.failed, JobStatus.dismissed)


def utcnow() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """A datetime stored naive in UTC and read back timezone-aware (SQLite drops the zone)."""

    impl = DateTime
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime given to the job store")
        return value.astimezone(UTC).replace(tzinfo=None)

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        return None if value is None else value.replace(tzinfo=UTC)


class Base(DeclarativeBase):
    pass


class JobRow(Base):
    """One registration job."""

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    status: Mapped[str] = mapped_column(String(16))
    stage: Mapped[str | None] = mapped_column(String(16))
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    message: Mapped[str | None] = mapped_column(Text)
    error: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    quality: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    timings: Mapped[dict[str, float] | None] = mapped_column(JSON)
    """Seconds per stage of a successful attempt (``matching``, ...), written by its worker."""
    options: Mapped[dict[str, Any]] = mapped_column(JSON)
    has_points: Mapped[bool] = mapped_column(Boolean, default=False)
    idempotency_key: Mapped[str | None] = mapped_column(String(255), unique=True)
    request_hash: Mapped[str | None] = mapped_column(String(64))
    owner: Mapped[str | None] = mapped_column(String(64))
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer)
    lease_owner: Mapped[str | None] = mapped_column(String(128))
    lease_expires: Mapped[datetime | None] = mapped_column(UTCDateTime)
    created: Mapped[datetime] = mapped_column(UTCDateTime)
    updated: Mapped[datetime] = mapped_column(UTCDateTime)
    started: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished: Mapped[datetime | None] = mapped_column(UTCDateTime)
    dispatched: Mapped[datetime | None] = mapped_column(UTCDateTime)
    """When the job was last handed to the broker (scale-out mode); None while accepted and not
    yet sent, or since it went back to ``accepted``."""
    # Webhook. ``callback`` holds the target URLs and the server's base URL; the other columns
    # are the outbox of the delivery of the job's last end (``webhook_event``: the status it
    # announces).
    callback: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    webhook_event: Mapped[str | None] = mapped_column(String(16))
    webhook_state: Mapped[str | None] = mapped_column(String(16))
    webhook_attempts: Mapped[int | None] = mapped_column(Integer)
    webhook_next: Mapped[datetime | None] = mapped_column(UTCDateTime)
    webhook_last: Mapped[datetime | None] = mapped_column(UTCDateTime)
    webhook_error: Mapped[str | None] = mapped_column(Text)
    webhook_delivery: Mapped[str | None] = mapped_column(String(32))

    __table_args__ = (
        Index("ix_jobs_status_created", "status", "created"),
        Index("ix_jobs_created", "created"),
        Index("ix_jobs_owner_status", "owner", "status"),
        Index("ix_jobs_webhook_due", "webhook_state", "webhook_next"),
    )


@dataclass(frozen=True)
class Job:
    """A snapshot of one job row (detached from any database session)."""

    id: str
    status: JobStatus
    stage: str | None
    progress: float
    message: str | None
    error: dict[str, Any] | None
    quality: dict[str, Any] | None
    options: dict[str, Any]
    has_points: bool
    idempotency_key: str | None
    request_hash: str | None
    owner: str | None
    attempts: int
    max_attempts: int
    lease_owner: str | None
    lease_expires: datetime | None
    created: datetime
    updated: datetime
    started: datetime | None
    finished: datetime | None
    callback: dict[str, Any] | None = None
    webhook_event: str | None = None
    webhook_state: str | None = None
    webhook_attempts: int | None = None
    webhook_next: datetime | None = None
    webhook_last: datetime | None = None
    webhook_error: str | None = None
    webhook_delivery: str | None = None
    timings: dict[str, float] | None = None
    dispatched: datetime | None = None

    @classmethod
    def from_row(cls, row: JobRow) -> Job:
        values = {name: getattr(row, name) for name in cls.__dataclass_fields__}
        values["status"] = JobStatus(row.status)
        return cls(**values)

    @property
    def duration(self) -> float | None:
        """Seconds from the start of the last attempt to the end, once finished."""
        if self.started is None or self.finished is None:
            return None
        return (self.finished - self.started).total_seconds()


class IdempotencyConflict(Exception):
    """An idempotency key was reused with a different request."""

    def __init__(self, job: Job) -> None:
        super().__init__(f"idempotency key already used by job {job.id} for another request")
        self.job = job


class SchemaError(RuntimeError):
    """The database's schema cannot be brought to the revision this release needs."""


class SchemaBehind(SchemaError):
    """The database's schema is at an older revision (or has none yet): the API upgrades it."""


def _sqlite_pragmas(dbapi_connection: Any, connection_record: Any) -> None:
    cursor = dbapi_connection.cursor()
    # WAL lets readers and one writer work together across processes; the busy timeout makes
    # writers wait instead of failing. FULL sync: every commit (an accepted job above all) is
    # on disk before it returns, as a PostgreSQL commit is.
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=FULL")
    cursor.execute("PRAGMA busy_timeout=30000")
    cursor.close()


def make_engine(url: str) -> Engine:
    """Create an engine; SQLite gets WAL mode and a busy timeout for multi-process use."""
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False})
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    return create_engine(url, pool_pre_ping=True)


def alembic_config(connection: Any = None) -> Config:
    """The Alembic configuration of the job table, running over ``connection`` if given (else
    over the database of the ``PWLREG_*`` settings, for the ``alembic`` command)."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.attributes["connection"] = connection
    return config


class JobStore:
    """Create, read and move jobs through their life cycle.

    Parameters
    ----------
    engine : sqlalchemy.engine.Engine
        Engine of the job database; the schema is made by :meth:`create_schema`.
    """

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self._sessions = sessionmaker(engine, expire_on_commit=False)

    @classmethod
    def from_url(cls, url: str) -> JobStore:
        """A store over a new engine for ``url``."""
        return cls(make_engine(url))

    def create_schema(self) -> None:
        """Bring the database to the newest schema revision: create the table in an empty
        database, upgrade one made by an earlier release (also one made before the schema had
        revisions).

        Raises
        ------
        SchemaError
            The database is at a revision this release does not know (it was upgraded by a
            newer release), or an upgrade step failed; nothing was changed.
        """
        with self.engine.begin() as connection:
            if connection.dialect.name == "postgresql":
                # Processes starting together upgrade one after the other (released at commit).
                connection.execute(text("SELECT pg_advisory_xact_lock(:key)"),
                                   {"key": SCHEMA_LOCK})
            config = alembic_config(connection)
            head = ScriptDirectory.from_config(config).get_current_head()
            current = MigrationContext.configure(connection).get_current_revision()
            try:
                command.upgrade(config, "head")
            except CommandError as exc:
                raise SchemaError(
                    f"the job database {self._where()} is at schema revision {current!r}, "
                    f"which this release of pwlreg does not know (its newest is {head!r}): it "
                    "was upgraded by a newer release; run that release, or restore a backup "
                    f"made before the upgrade ({exc})"
                ) from None
            except Exception as exc:
                raise SchemaError(
                    f"the job database {self._where()} could not be upgraded from schema "
                    f"revision {current!r} to {head!r}: {type(exc).__name__}: {exc}"
                ) from exc

    def schema_revision(self) -> tuple[str | None, str | None]:
        """The database's schema revision and the newest this release knows."""
        with self.engine.connect() as connection:
            current = MigrationContext.configure(connection).get_current_revision()
        return current, ScriptDirectory.from_config(alembic_config()).get_current_head()

    def check_schema(self) -> None:
        """Raise unless the database is at the newest revision, for processes that use the
        store but leave upgrades to the API.

        Raises
        ------
        SchemaBehind
            The database has no schema yet, or an older revision.
        SchemaError
            The database is at a revision this release does not know (a newer release's).
        """
        current, head = self.schema_revision()
        if current == head:
            return
        script = ScriptDirectory.from_config(alembic_config())
        known = {rev.revision for rev in script.walk_revisions()}
        if current is None or current in known:
            raise SchemaBehind(
                f"the job database {self._where()} is at schema revision {current!r}, this "
                f"release of pwlreg needs {head!r}: the API of this release upgrades it when it "
                "starts"
            )
        raise SchemaError(
            f"the job database {self._where()} is at schema revision {current!r}, which this "
            f"release of pwlreg does not know (its newest is {head!r}): it was upgraded by a "
            "newer release; run that release"
        )

    def _where(self) -> str:
        return self.engine.url.render_as_string(hide_password=True)

    def dispose(self) -> None:
        """Close the connections of the engine."""
        self.engine.dispose()

    def ping(self) -> bool:
        """True if the database answers a trivial query."""
        with self.engine.connect() as connection:
            connection.execute(text("SELECT 1"))
        return True

    def _update_owned(self, job_id: str, owner: str, values: dict[str, Any]) -> bool:
        """Apply ``values`` to a job still running under ``owner``'s lease; False otherwise."""
        statement = (
            update(JobRow)
            .where(
                JobRow.id == job_id,
                JobRow.status == JobStatus.running.value,
                JobRow.lease_owner == owner,
            )
            .values(**values)
        )
        return self._update(statement) == 1

    def _update(self, statement: Any) -> int:
        # A plain connection: an ORM session costs about three times as much per update
        # (measured), and the workers update their job several times per job.
        with self.engine.begin() as connection:
            return connection.execute(statement).rowcount

    # --- creation and reading ----------------------------------------------------------------

    def create(
        self,
        job_id: str,
        options: dict[str, Any],
        has_points: bool,
        max_attempts: int,
        idempotency_key: str | None = None,
        request_hash: str | None = None,
        owner: str | None = None,
        callback: dict[str, Any] | None = None,
    ) -> tuple[Job, bool]:
        """Insert an accepted job, or return the job already created with the same key.

        ``owner`` is the API client submitting it (None without API keys); the caller scopes
        ``idempotency_key`` to the owner (see :func:`service.api.jobs.scoped_key`).
        ``callback`` is the job's webhook (see :mod:`service.webhooks`), if any.

        Returns
        -------
        job : Job
            The new job, or the existing one for ``idempotency_key``.
        created : bool
            False if the job existed already.

        Raises
        ------
        IdempotencyConflict
            If the key is known but was sent with a different request (``request_hash``).
        """
        if idempotency_key is not None:
            existing = self.get_by_idempotency_key(idempotency_key)
            if existing is not None:
                return self._replay(existing, request_hash), False
        now = utcnow()
        row = JobRow(
            id=job_id,
            status=JobStatus.accepted.value,
            stage=None,
            progress=0.0,
            options=options,
            has_points=has_points,
            idempotency_key=idempotency_key,
            request_hash=request_hash,
            owner=owner,
            callback=callback,
            attempts=0,
            max_attempts=max_attempts,
            created=now,
            updated=now,
        )
        try:
            with self._sessions.begin() as session:
                session.add(row)
        except IntegrityError:
            # Two requests with the same key raced; the other one won.
            existing = (
                self.get_by_idempotency_key(idempotency_key) if idempotency_key else None
            )
            if existing is None:
                raise
            return self._replay(existing, request_hash), False
        return Job.from_row(row), True

    @staticmethod
    def _replay(existing: Job, request_hash: str | None) -> Job:
        if existing.request_hash != request_hash:
            raise IdempotencyConflict(existing)
        return existing

    def get(self, job_id: str) -> Job | None:
        """The job ``job_id``, or None."""
        with self._sessions() as session:
            row = session.get(JobRow, job_id)
            return None if row is None else Job.from_row(row)

    def get_by_idempotency_key(self, key: str) -> Job | None:
        """The job created with idempotency key ``key``, or None."""
        with self._sessions() as session:
            row = session.scalars(select(JobRow).where(JobRow.idempotency_key == key)).first()
            return None if row is None else Job.from_row(row)

    def list(
        self,
        statuses: Iterable[JobStatus] = (),
        limit: int = 20,
        offset: int = 0,
        owner: str | None = None,
    ) -> tuple[list[Job], int]:
        """Jobs newest first, optionally only those with one of ``statuses`` and only those of
        ``owner`` (None: every job).

        Returns
        -------
        jobs : list of Job
            At most ``limit`` jobs, skipping the first ``offset``.
        matched : int
            Number of jobs matching the filter.
        """
        wanted = [s.value for s in statuses]
        query = select(JobRow)
        count = select(func.count()).select_from(JobRow)
        if wanted:
            query = query.where(JobRow.status.in_(wanted))
            count = count.where(JobRow.status.in_(wanted))
        if owner is not None:
            query = query.where(JobRow.owner == owner)
            count = count.where(JobRow.owner == owner)
        query = query.order_by(JobRow.created.desc(), JobRow.id.desc()).limit(limit).offset(offset)
        with self._sessions() as session:
            rows = session.scalars(query).all()
            matched = session.execute(count).scalar_one()
        return [Job.from_row(r) for r in rows], int(matched)

    def count_by_status(self) -> dict[JobStatus, int]:
        """Number of jobs in each status (every status present, zeros included)."""
        with self._sessions() as session:
            pairs = session.execute(
                select(JobRow.status, func.count()).group_by(JobRow.status)
            ).all()
        counts = {status: 0 for status in JobStatus}
        for status, n in pairs:
            counts[JobStatus(status)] = int(n)
        return counts

    def count_accepted(self, owner: str | None = None) -> int:
        """Number of jobs waiting for a worker, only those of ``owner`` if given."""
        query = (
            select(func.count()).select_from(JobRow)
            .where(JobRow.status == JobStatus.accepted.value)
        )
        if owner is not None:
            query = query.where(JobRow.owner == owner)
        with self._sessions() as session:
            return int(session.execute(query).scalar_one())

    def next_accepted(self, limit: int, exclude: Sequence[str] = ()) -> list[str]:
        """Ids of the oldest accepted jobs (first in, first out), skipping ``exclude``."""
        query = select(JobRow.id).where(JobRow.status == JobStatus.accepted.value)
        if exclude:
            query = query.where(JobRow.id.not_in(list(exclude)))
        query = query.order_by(JobRow.created, JobRow.id).limit(limit)
        with self._sessions() as session:
            return list(session.scalars(query).all())

    def unfinished_ids(self) -> list[str]:
        """Ids of the jobs accepted or running."""
        query = select(JobRow.id).where(
            JobRow.status.in_([JobStatus.accepted.value, JobStatus.running.value])
        )
        with self._sessions() as session:
            return list(session.scalars(query).all())

    def statuses(self, job_ids: Sequence[str]) -> dict[str, JobStatus]:
        """The status of each of ``job_ids`` that has a row."""
        found: dict[str, JobStatus] = {}
        ids = list(job_ids)
        with self._sessions() as session:
            for i in range(0, len(ids), 500):
                rows = session.execute(
                    select(JobRow.id, JobRow.status).where(JobRow.id.in_(ids[i:i + 500]))
                ).all()
                found.update((job_id, JobStatus(status)) for job_id, status in rows)
        return found

    # --- dispatch to a broker (scale-out mode, see service.queue.CeleryQueue) -------------------

    def undispatched(self, limit: int, sent_before: datetime) -> list[str]:
        """Ids of the oldest accepted jobs never handed to the broker, or last handed before
        ``sent_before`` (their message may be lost)."""
        query = (
            select(JobRow.id)
            .where(
                JobRow.status == JobStatus.accepted.value,
                or_(JobRow.dispatched.is_(None), JobRow.dispatched < sent_before),
            )
            .order_by(JobRow.created, JobRow.id)
            .limit(limit)
        )
        with self._sessions() as session:
            return list(session.scalars(query).all())

    def mark_dispatched(self, job_id: str, sent_before: datetime) -> bool:
        """Record that a message for the accepted job ``job_id`` is being sent now; False if
        the job is not accepted or another process sent one after ``sent_before``."""
        return self._update(
            update(JobRow)
            .where(
                JobRow.id == job_id,
                JobRow.status == JobStatus.accepted.value,
                or_(JobRow.dispatched.is_(None), JobRow.dispatched < sent_before),
            )
            .values(dispatched=utcnow())
        ) == 1

    def unmark_dispatched(self, job_id: str) -> None:
        """Forget a dispatch whose message could not be sent (it is sent again)."""
        self._update(
            update(JobRow)
            .where(JobRow.id == job_id, JobRow.status == JobStatus.accepted.value)
            .values(dispatched=None)
        )

    # --- transitions by a worker --------------------------------------------------------------

    def claim(self, job_id: str, owner: str, lease_seconds: float) -> Job | None:
        """Move a job to running under ``owner``'s lease, counting one more attempt; None if it
        is neither accepted nor running under an expired lease with attempts left (a worker
        that died; the broker delivers its job again)."""
        now = utcnow()
        takeable = or_(
            JobRow.status == JobStatus.accepted.value,
            and_(
                JobRow.status == JobStatus.running.value,
                JobRow.lease_expires < now,
                JobRow.attempts < JobRow.max_attempts,
            ),
        )
        n = self._update(
            update(JobRow)
            .where(JobRow.id == job_id, takeable)
            .values(
                status=JobStatus.running.value,
                attempts=JobRow.attempts + 1,
                lease_owner=owner,
                lease_expires=now + timedelta(seconds=lease_seconds),
                started=now,
                updated=now,
                stage=None,
                progress=0.0,
            )
        )
        return self.get(job_id) if n == 1 else None

    def renew(
        self,
        job_id: str,
        owner: str,
        lease_seconds: float,
        stage: str | None = None,
        progress: float | None = None,
    ) -> bool:
        """Extend ``owner``'s lease and record the progress; False if the job is no longer
        running under this owner (dismissed, or taken over after the lease expired)."""
        now = utcnow()
        values: dict[str, Any] = {
            "lease_expires": now + timedelta(seconds=lease_seconds),
            "updated": now,
        }
        if stage is not None:
            values["stage"] = stage
        if progress is not None:
            values["progress"] = progress
        return self._update_owned(job_id, owner, values)

    def finish(
        self,
        job_id: str,
        owner: str,
        status: JobStatus,
        message: str | None,
        error: dict[str, Any] | None = None,
        quality: dict[str, Any] | None = None,
        timings: dict[str, float] | None = None,
    ) -> bool:
        """End ``owner``'s attempt with ``status`` (successful or failed), and the seconds
        per stage of a successful one; False if the job is no longer running under this
        owner."""
        now = utcnow()
        values: dict[str, Any] = {
            "status": status.value,
            "message": message,
            "error": error,
            "quality": quality,
            "timings": timings,
            "finished": now,
            "updated": now,
            "lease_owner": None,
            "lease_expires": None,
        }
        if status == JobStatus.successful:
            values["progress"] = 100.0
        return self._update_owned(job_id, owner, values)

    def release(self, job_id: str, owner: str, message: str) -> bool:
        """Give a running job back to the queue without counting the attempt (the worker is
        shutting down, not failing)."""
        values = {
            "status": JobStatus.accepted.value,
            "attempts": JobRow.attempts - 1,
            "lease_owner": None,
            "lease_expires": None,
            "stage": None,
            "progress": 0.0,
            "message": message,
            "updated": utcnow(),
            "dispatched": None,
        }
        return self._update_owned(job_id, owner, values)

    # --- transitions by the API and the maintenance pass ------------------------------------

    def dismiss(self, job_id: str) -> Job | None:
        """Mark a job dismissed (cancelled by its client); None if it does not exist."""
        now = utcnow()
        self._update(
            update(JobRow)
            .where(JobRow.id == job_id, JobRow.status != JobStatus.dismissed.value)
            .values(
                status=JobStatus.dismissed.value,
                message="dismissed by the client",
                finished=now,
                updated=now,
                lease_owner=None,
                lease_expires=None,
            )
        )
        return self.get(job_id)

    def recover_expired(
        self, failure: Callable[[str], dict[str, Any]], now: datetime | None = None
    ) -> tuple[list[str], list[str]]:
        """Requeue running jobs whose lease expired; fail those out of attempts, with the error
        document ``failure(message)``.

        Returns
        -------
        requeued, failed : list of str
            Ids of the jobs put back to ``accepted`` and of those that failed for good.
        """
        now = now or utcnow()
        with self._sessions() as session:
            expired = session.execute(
                select(JobRow.id, JobRow.attempts, JobRow.max_attempts).where(
                    JobRow.status == JobStatus.running.value, JobRow.lease_expires < now
                )
            ).all()
        requeued: list[str] = []
        failed: list[str] = []
        for job_id, attempts, max_attempts in expired:
            # The same conditions again, so that a lease renewed meanwhile wins.
            still_expired = (
                JobRow.id == job_id,
                JobRow.status == JobStatus.running.value,
                JobRow.lease_expires < now,
            )
            if attempts >= max_attempts:
                message = (
                    f"the worker running this job stopped {attempts} times (process killed, "
                    f"out of memory or server restarted); gave up after {max_attempts} attempts"
                )
                error = failure(message)
                n = self._update(
                    update(JobRow)
                    .where(*still_expired)
                    .values(
                        status=JobStatus.failed.value,
                        message=message,
                        error=error,
                        finished=now,
                        updated=now,
                        lease_owner=None,
                        lease_expires=None,
                    )
                )
                if n:
                    failed.append(job_id)
            else:
                n = self._update(
                    update(JobRow)
                    .where(*still_expired)
                    .values(
                        status=JobStatus.accepted.value,
                        message=f"requeued after attempt {attempts} of {max_attempts} was "
                        "interrupted",
                        stage=None,
                        progress=0.0,
                        updated=now,
                        lease_owner=None,
                        lease_expires=None,
                        dispatched=None,
                    )
                )
                if n:
                    requeued.append(job_id)
        return requeued, failed

    def expired_finished(self, older_than: datetime, limit: int = 500) -> list[str]:
        """Ids of finished jobs whose end is before ``older_than``."""
        with self._sessions() as session:
            return list(
                session.scalars(
                    select(JobRow.id)
                    .where(
                        JobRow.status.in_([s.value for s in FINISHED]),
                        JobRow.finished < older_than,
                    )
                    .limit(limit)
                ).all()
            )

    def delete(self, job_ids: Sequence[str]) -> int:
        """Delete job rows; returns how many existed."""
        if not job_ids:
            return 0
        with self._sessions.begin() as session:
            n = 0
            for job_id in job_ids:
                row = session.get(JobRow, job_id)
                if row is not None:
                    session.delete(row)
                    n += 1
            return n

    def existing_ids(self, job_ids: Sequence[str]) -> set[str]:
        """The subset of ``job_ids`` that have a row."""
        if not job_ids:
            return set()
        with self._sessions() as session:
            return set(session.scalars(select(JobRow.id).where(JobRow.id.in_(list(job_ids)))))

    # --- webhook outbox (see service.webhooks) ---------------------------------------------------

    def arm_webhooks(self, target: Any, limit: int = 100) -> list[str]:
        """Open a delivery for every finished job with a callback whose current end has none
        yet. ``target(job)`` gives the URL of that end (None: nothing to send, the delivery is
        recorded as ``skipped``). Returns the ids of the jobs armed."""
        finished = [s.value for s in FINISHED]
        with self._sessions() as session:
            rows = session.scalars(
                select(JobRow)
                .where(
                    JobRow.callback.is_not(None),
                    JobRow.status.in_(finished),
                    (JobRow.webhook_event.is_(None)) | (JobRow.webhook_event != JobRow.status),
                )
                .limit(limit)
            ).all()
            jobs = [Job.from_row(r) for r in rows]
        armed: list[str] = []
        now = utcnow()
        for job in jobs:
            url = target(job)
            n = self._update(
                update(JobRow)
                .where(
                    JobRow.id == job.id,
                    JobRow.status == job.status.value,
                    (JobRow.webhook_event.is_(None)) | (JobRow.webhook_event != JobRow.status),
                )
                .values(
                    webhook_event=job.status.value,
                    webhook_state="pending" if url else "skipped",
                    webhook_attempts=0,
                    webhook_next=now if url else None,
                    webhook_last=None,
                    webhook_error=None,
                    webhook_delivery=uuid.uuid4().hex,
                )
            )
            if n:
                armed.append(job.id)
        return armed

    def due_webhooks(self, now: datetime, limit: int = 20) -> list[Job]:
        """Jobs whose pending delivery is due at ``now``, the most overdue first."""
        with self._sessions() as session:
            rows = session.scalars(
                select(JobRow)
                .where(JobRow.webhook_state == "pending", JobRow.webhook_next <= now)
                .order_by(JobRow.webhook_next)
                .limit(limit)
            ).all()
            return [Job.from_row(r) for r in rows]

    def next_webhook_time(self) -> datetime | None:
        """When the next pending delivery is due, or None."""
        with self._sessions() as session:
            return session.execute(
                select(func.min(JobRow.webhook_next)).where(JobRow.webhook_state == "pending")
            ).scalar_one()

    def claim_webhook(self, job: Job, hold_seconds: float) -> bool:
        """Take the due delivery of ``job`` for one attempt (its next time moves
        ``hold_seconds`` ahead, so that nobody else takes it meanwhile); False if it was taken,
        finished or replaced by a newer end."""
        now = utcnow()
        return self._update(
            update(JobRow)
            .where(
                JobRow.id == job.id,
                JobRow.webhook_state == "pending",
                JobRow.webhook_delivery == job.webhook_delivery,
                JobRow.webhook_next <= now,
            )
            .values(webhook_next=now + timedelta(seconds=hold_seconds))
        ) == 1

    def record_webhook(
        self,
        job_id: str,
        delivery: str,
        attempts: int,
        state: str,
        error: str | None,
        next_time: datetime | None,
    ) -> bool:
        """Record the outcome of an attempt of delivery ``delivery``; False if that delivery
        was replaced (the job ended again) or the job is gone."""
        return self._update(
            update(JobRow)
            .where(JobRow.id == job_id, JobRow.webhook_delivery == delivery)
            .values(
                webhook_attempts=attempts,
                webhook_state=state,
                webhook_error=error,
                webhook_next=next_time,
                webhook_last=utcnow(),
            )
        ) == 1
