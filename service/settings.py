"""Service settings, read from ``PWLREG_*`` environment variables (pydantic-settings).

Every setting has a default that works on a fresh machine: a SQLite database and the artifacts of
the jobs under ``./data``, one worker process per CPU core.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


def _default_workers() -> int:
    """CPU cores this process may use (the affinity mask of a container, if any)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not on Linux
        return max(1, os.cpu_count() or 1)


class Settings(BaseSettings):
    """Settings of the pwlreg service.

    Each field ``name`` is read from the environment variable ``PWLREG_<NAME>`` (case-insensitive)
    or from a ``.env`` file in the working directory. Durations are in seconds, sizes in bytes.
    """

    model_config = SettingsConfigDict(
        env_prefix="PWLREG_", env_file=".env", extra="ignore", frozen=True
    )

    data_dir: Path = Field(
        Path("data"),
        description="Directory of the SQLite database (default URL), the uploaded inputs and the "
        "results of every job. Created if missing.",
    )
    database_url: str | None = Field(
        None,
        description="SQLAlchemy database URL of the job store. Default: "
        "sqlite:///<data_dir>/pwlreg.db.",
    )
    workers: int = Field(
        default_factory=_default_workers,
        ge=1,
        le=256,
        description="Number of worker processes running registrations in parallel "
        "(default: the number of CPU cores).",
    )
    worker_threads: int = Field(
        1,
        ge=1,
        le=256,
        description="Threads each worker process gives to its numerical libraries (OpenCV, numba, "
        "BLAS, OpenMP). Keep workers x worker_threads at most the number of cores.",
    )
    max_upload_bytes: int = Field(
        64 * 1024 * 1024,
        ge=1024,
        description="Largest accepted part of an upload (each image, the points, the options), in "
        "bytes. A larger part is refused with 413 while it streams, before it is stored.",
    )
    max_pixels: int = Field(
        40_000_000,
        ge=4,
        description="Largest accepted image decoded whole, in pixels (width x height), checked "
        "from the image header before decoding (decompression bombs are refused with 422).",
    )
    max_raster_pixels: int = Field(
        1_000_000_000,
        ge=4,
        le=2**30,
        description="Largest accepted TIFF (GeoTIFF) over 16.8 MP, in pixels: such rasters are "
        "read window by window and registered on a reduced level, in a memory that does not "
        "grow with them (under 1 GB), so this limit bounds a job's time, not its memory. "
        "Their upload must also fit max_upload_bytes.",
    )
    job_time_limit: float = Field(
        1800.0,
        gt=0,
        description="Wall-clock limit of one attempt of a job, in seconds; a job over it fails.",
    )
    retention: float = Field(
        7 * 24 * 3600.0,
        gt=0,
        description="Finished jobs (successful, failed, dismissed) older than this many seconds "
        "are deleted with their files.",
    )
    lease_seconds: float = Field(
        30.0,
        gt=0,
        description="Lease of a running job, in seconds. The worker renews it while it runs; a job "
        "whose lease expired (its process died) goes back to the queue.",
    )
    max_attempts: int = Field(
        3,
        ge=1,
        le=100,
        description="Attempts of a job before it fails for good when its worker keeps dying.",
    )
    progress_interval: float = Field(
        0.25,
        gt=0,
        description="Minimum interval between two progress (and lease) updates a worker writes "
        "to the database, in seconds.",
    )
    maintenance_interval: float = Field(
        60.0,
        gt=0,
        description="Interval of the maintenance pass (expired leases, retention), in seconds.",
    )
    api_keys: SecretStr | None = Field(
        None,
        description="API keys, comma-separated, each 'name:key' or a bare 'key' (named client1, "
        "client2, ... in order). With any key configured, every endpoint but /healthz, /readyz, "
        "/docs and /openapi.json needs 'Authorization: Bearer <key>', and each client sees only "
        "its own jobs. Default: no keys, no access control.",
    )
    api_keys_file: Path | None = Field(
        None,
        description="Text file of API keys, one 'name key' per line ('#' starts a comment), "
        "added to api_keys.",
    )
    max_queued_jobs: int = Field(
        1000,
        ge=1,
        description="Most jobs waiting for a worker (status accepted) in all; a submission "
        "beyond is refused with 429 and Retry-After.",
    )
    max_queued_per_client: int = Field(
        100,
        ge=1,
        description="Most jobs waiting for a worker per API client (with API keys only); a "
        "submission beyond is refused with 429 and Retry-After.",
    )
    min_free_bytes: int = Field(
        256 * 1024 * 1024,
        ge=0,
        description="Free space the data directory must keep: a submission (its declared "
        "length included) that would leave less is refused with 507 before it is received.",
    )
    webhook_secret: SecretStr | None = Field(
        None,
        description="Key of the HMAC-SHA256 signature of every webhook delivery "
        "(X-Pwlreg-Signature). Default: a random key generated at the first start and kept in "
        "<data_dir>/webhook_secret.",
    )
    webhook_allow: str | None = Field(
        None,
        description="Webhook targets allowed although they resolve to a loopback, link-local, "
        "private, multicast, reserved or unspecified address, comma-separated: host names, IP "
        "addresses or CIDR networks (e.g. '127.0.0.1' for a local receiver). Default: none.",
    )
    webhook_max_attempts: int = Field(
        5,
        ge=1,
        le=50,
        description="Attempts of a webhook delivery before it is given up (recorded as failed).",
    )
    webhook_retry_delay: float = Field(
        10.0,
        gt=0,
        description="Delay before the second attempt of a webhook delivery, in seconds; it "
        "doubles after every further failed attempt.",
    )
    webhook_timeout: float = Field(
        5.0,
        gt=0,
        le=60,
        description="Timeout of one webhook attempt (connect, send, answer), in seconds.",
    )
    href_allow: str | None = Field(
        None,
        description="Origins the service may read OGC API - Processes inputs given by reference "
        "(href) from, comma-separated 'scheme://host[:port]' (http or https; without a port, "
        "the scheme's default). A host name must resolve to public addresses only; a "
        "loopback, private or other non-public address is allowed only when an entry names "
        "it as an IP address. Default: none (inputs by reference are refused).",
    )
    href_timeout: float = Field(
        30.0,
        gt=0,
        le=600,
        description="Longest time the service spends reading one input given by reference "
        "(connect, answer and the whole body), in seconds. Each input is also limited to "
        "max_upload_bytes.",
    )
    log_format: Literal["text", "json"] = Field(
        "text",
        description="Format of the log records of the API and worker processes: 'text' (one "
        "readable line each) or 'json' (one JSON object per line with time, level, logger, "
        "message and, for a record about a job, job_id and client).",
    )
    queue: Literal["local", "celery"] = Field(
        "local",
        description="Where registrations run: 'local', a pool of worker processes of the API "
        "process (embedded mode), or 'celery', the workers started by 'pwlreg worker' on any "
        "machine, reached through the broker (broker_url); the API process then runs none.",
    )
    broker_url: str | None = Field(
        None,
        description="Celery broker URL of the 'celery' queue, e.g. redis://redis:6379/0 or "
        "amqp://user:password@rabbitmq:5672//.",
    )
    broker_queue: str = Field(
        "pwlreg",
        min_length=1,
        max_length=200,
        description="Name of the broker queue of the jobs (services sharing a broker use "
        "different names).",
    )
    runner: str = Field(
        "pwlreg.core.scaled:register",
        description="Import path (module:function) of the registration function the workers "
        "call. Change it only to wrap core, e.g. in tests.",
    )

    @model_validator(mode="after")
    def _lease_outlives_progress(self) -> Settings:
        if self.progress_interval * 2 > self.lease_seconds:
            raise ValueError("lease_seconds must be at least twice progress_interval")
        return self

    @model_validator(mode="after")
    def _celery_needs_a_broker(self) -> Settings:
        if self.queue == "celery" and not self.broker_url:
            raise ValueError("queue 'celery' needs broker_url (PWLREG_BROKER_URL)")
        return self

    @property
    def resolved_database_url(self) -> str:
        """The database URL, defaulting to a SQLite file in :attr:`data_dir`."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'pwlreg.db').resolve()}"
