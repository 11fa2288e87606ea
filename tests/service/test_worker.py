"""The job store, the worker and the maintenance pass in-process, over a real SQLite file and a
real data directory, with registration functions injected into the worker."""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from datetime import timedelta
from pathlib import Path

import cv2
import numpy as np
import pytest
from sqlalchemy import update

from pwlreg.core.options import RegistrationOptions
from pwlreg.core.pipeline import register
from pwlreg.service.logs import JsonFormatter
from pwlreg.service.maintenance import Janitor
from pwlreg.service.metrics import Metrics
from pwlreg.service.settings import Settings
from pwlreg.service.storage import LocalStorage
from pwlreg.service.store import IdempotencyConflict, JobRow, JobStatus, utcnow
from pwlreg.service.worker import (
    JobDismissed,
    ProgressReporter,
    TimeLimitExceeded,
    WorkerContext,
    run_job,
    stage_timings,
)
from tests.service.helpers import Pair, metric_samples, one

DEFAULTS = RegistrationOptions().model_dump(mode="json")


class RecordingQueue:
    """Stands in for the queue of the janitor: records what it is told."""

    def __init__(self) -> None:
        self.enqueued: list[str] = []

    def enqueue(self, job_id: str) -> None:
        self.enqueued.append(job_id)


@pytest.fixture()
def settings(tmp_path: Path) -> Settings:
    return Settings(_env_file=None, data_dir=tmp_path / "data", lease_seconds=1.0,  # type: ignore[call-arg]
                    progress_interval=0.05, max_attempts=2, job_time_limit=30)


@pytest.fixture()
def context(settings: Settings) -> WorkerContext:
    ctx = WorkerContext.from_settings(settings)
    ctx.storage.prepare()
    ctx.store.create_schema()
    return ctx


def add_job(ctx: WorkerContext, pair: Pair, key: str | None = None) -> str:
    staging = ctx.storage.new_staging()
    (staging / "reference").write_bytes(pair.reference_png)
    (staging / "moving").write_bytes(pair.moving_png)
    (staging / "points").write_bytes(pair.points_json)
    job_id = os.urandom(16).hex()
    ctx.storage.commit_inputs(staging, job_id)
    job, created = ctx.store.create(job_id, DEFAULTS, True, ctx.settings.max_attempts, key, "h")
    assert created
    return job.id


# --- store -------------------------------------------------------------------------------------


def test_only_one_worker_claims_a_job(context: WorkerContext, pair: Pair) -> None:
    job_id = add_job(context, pair)
    store = context.store
    results: list[object] = []
    barrier = threading.Barrier(4)

    def claim(owner: str) -> None:
        barrier.wait()
        results.append(store.claim(job_id, owner, 5.0))

    threads = [threading.Thread(target=claim, args=(f"w{i}",)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    winners = [r for r in results if r is not None]
    assert len(winners) == 1
    owner = winners[0].lease_owner  # type: ignore[attr-defined]
    assert store.renew(job_id, owner, 5.0, stage="matching", progress=10)
    assert not store.renew(job_id, "someone-else", 5.0)
    assert not store.finish(job_id, "someone-else", JobStatus.successful, "x")
    job = store.get(job_id)
    assert job is not None and (job.stage, job.progress, job.attempts) == ("matching", 10, 1)


def test_idempotency_key_with_another_request_is_a_conflict(
    context: WorkerContext, pair: Pair
) -> None:
    job_id = add_job(context, pair, key="k1")
    again, created = context.store.create("other", DEFAULTS, True, 2, "k1", "h")
    assert not created and again.id == job_id
    with pytest.raises(IdempotencyConflict):
        context.store.create("third", DEFAULTS, True, 2, "k1", "different")


def test_expired_leases_are_requeued_then_failed_after_the_last_attempt(
    context: WorkerContext, pair: Pair
) -> None:
    store = context.store
    queue = RecordingQueue()
    janitor = Janitor(context.settings, store, context.storage, queue)  # type: ignore[arg-type]
    job_id = add_job(context, pair)
    assert store.claim(job_id, "dead-1", lease_seconds=0.01)
    time.sleep(0.05)
    assert janitor.recover() == ([job_id], [])
    assert queue.enqueued == [job_id]
    job = store.get(job_id)
    assert job is not None and job.status == JobStatus.accepted and "attempt 1 of 2" in job.message

    assert store.claim(job_id, "dead-2", lease_seconds=0.01)
    time.sleep(0.05)
    assert janitor.recover() == ([], [job_id])
    job = store.get(job_id)
    assert job is not None and job.status == JobStatus.failed
    assert job.error is not None and job.error["type"].endswith("attempts-exhausted")
    assert "2 attempts" in job.message

    # A live lease is left alone.
    other = add_job(context, pair)
    assert store.claim(other, "alive", lease_seconds=60)
    assert janitor.recover() == ([], [])


def test_retention_deletes_expired_jobs_and_their_files(
    context: WorkerContext, pair: Pair
) -> None:
    store, storage = context.store, context.storage
    old, recent, running = (add_job(context, pair) for _ in range(3))
    store.dismiss(old)
    store.dismiss(recent)
    assert store.claim(running, "w", 60)
    long_ago = utcnow() - timedelta(seconds=context.settings.retention + 60)
    with store.engine.begin() as conn:
        conn.execute(update(JobRow).where(JobRow.id == old).values(finished=long_ago))
    janitor = Janitor(context.settings, store, storage, RecordingQueue())  # type: ignore[arg-type]
    assert janitor.apply_retention() == 1
    assert store.get(old) is None and not (storage.jobs / old).exists()
    assert store.get(recent) is not None and (storage.jobs / recent).exists()
    assert store.get(running) is not None


# --- progress reporter ---------------------------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_progress_reports_stay_in_memory_until_the_heartbeat(
    context: WorkerContext, pair: Pair
) -> None:
    job_id = add_job(context, pair)
    assert context.store.claim(job_id, "me", 5.0)
    reporter = ProgressReporter(context, job_id, "me", clock=FakeClock())
    writes = 0
    original = context.store.renew

    def counting_renew(*args: object, **kwargs: object) -> bool:
        nonlocal writes
        writes += 1
        return original(*args, **kwargs)  # type: ignore[arg-type]

    context.store.renew = counting_renew  # type: ignore[method-assign]
    for i in range(1000):
        reporter("optimizing", i / 1000)
    reporter("optimizing", 0.2)  # progress never goes back
    assert writes == 0  # the registration's reports cost no database access
    reporter.beat()
    job = context.store.get(job_id)
    assert writes == 1
    assert job is not None and job.stage == "optimizing" and 85 < job.progress <= 90
    reporter("rendering", 0.5)
    reporter.beat()
    job = context.store.get(job_id)
    assert job is not None and job.stage == "rendering" and 90 < job.progress < 99


def test_dismissal_found_by_the_heartbeat_stops_the_next_report(
    context: WorkerContext, pair: Pair
) -> None:
    job_id = add_job(context, pair)
    assert context.store.claim(job_id, "me", 5.0)
    reporter = ProgressReporter(context, job_id, "me")
    with reporter.running():
        reporter("matching", 0.0)
        context.store.dismiss(job_id)
        deadline = time.monotonic() + 5
        with pytest.raises(JobDismissed):
            while time.monotonic() < deadline:
                reporter("matching", 0.5)
                time.sleep(0.01)


def test_time_limit_is_checked_at_every_report(context: WorkerContext, pair: Pair) -> None:
    job_id = add_job(context, pair)
    assert context.store.claim(job_id, "me", 5.0)
    clock = FakeClock()
    reporter = ProgressReporter(context, job_id, "me", clock=clock)
    reporter("matching", 0.1)
    clock.now += context.settings.job_time_limit + 1
    with pytest.raises(TimeLimitExceeded):
        reporter("matching", 0.2)


# --- run_job with injected registration functions ---------------------------------------


def test_a_bug_in_the_registration_fails_the_job_with_a_problem(
    context: WorkerContext, pair: Pair
) -> None:
    def broken(*args: object, **kwargs: object) -> object:
        raise ZeroDivisionError("oops")

    context.runner = broken
    job_id = add_job(context, pair)
    assert run_job(job_id, context) == "failed"
    job = context.store.get(job_id)
    assert job is not None and job.error is not None
    assert job.error["type"] == "urn:pwlreg:problem:internal-error"
    assert "ZeroDivisionError: oops" in job.error["detail"]
    assert not list((context.storage.jobs / job_id).glob("work-*"))


def test_time_limit_fails_the_job(context: WorkerContext, pair: Pair) -> None:
    context.settings = context.settings.model_copy(update={"job_time_limit": 0.2})

    def endless(reference, moving, points=None, options=None, progress=None):  # noqa: ANN001
        while True:
            progress("optimizing", 0.1)
            time.sleep(0.01)

    context.runner = endless
    job_id = add_job(context, pair)
    assert run_job(job_id, context) == "failed"
    job = context.store.get(job_id)
    assert job is not None and job.error is not None
    assert job.error["type"].endswith("time-limit-exceeded") and "0.2 s" in job.message


def test_dismissal_is_not_swallowed_by_a_broad_except(context: WorkerContext, pair: Pair) -> None:
    job_id = add_job(context, pair)
    calls = 0

    def stubborn(reference, moving, points=None, options=None, progress=None):  # noqa: ANN001
        nonlocal calls
        while True:
            calls += 1
            if calls == 3:
                context.store.dismiss(job_id)
            try:
                progress("optimizing", 0.5)
            except Exception:  # noqa: BLE001 (what careless code does)
                pass
            time.sleep(0.06)
            if calls > 100:
                raise AssertionError("the dismissal did not stop the registration")

    context.runner = stubborn
    assert run_job(job_id, context) == "dismissed"
    assert calls < 10
    assert not (context.storage.jobs / job_id).exists()
    assert run_job(job_id, context) == "skipped"  # a dismissed job is never claimed again


def test_a_job_dismissed_while_its_files_are_written_is_no_internal_error(
    context: WorkerContext, pair: Pair, caplog: pytest.LogCaptureFixture
) -> None:
    job_id = add_job(context, pair)

    def dismissed_under_it(reference, moving, points=None, options=None, progress=None):  # noqa: ANN001
        # As DELETE does while the results are written: the row, then every file of the job,
        # and the writer then finds its directory gone.
        context.store.dismiss(job_id)
        context.storage.remove(job_id)
        raise FileNotFoundError(f"{context.storage.jobs / job_id}/work/mesh.json")

    context.runner = dismissed_under_it
    with caplog.at_level(logging.INFO, logger="pwlreg"):
        assert run_job(job_id, context) == "dismissed"
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
    job = context.store.get(job_id)
    assert job is not None and job.status == JobStatus.dismissed and job.error is None
    assert not (context.storage.jobs / job_id).exists()


def test_an_attempt_taken_over_leaves_the_files_of_its_successor(
    context: WorkerContext, pair: Pair
) -> None:
    """An attempt that stalled past its lease and was taken over ends without a trace: not
    a write to the job, not a file of the attempt that took over (writing its results)."""
    job_id = add_job(context, pair)
    expire = update(JobRow).where(JobRow.id == job_id).values(
        lease_expires=utcnow() - timedelta(seconds=1))
    work: list[Path] = []

    def stalled(reference, moving, points=None, options=None, progress=None):  # noqa: ANN001
        # Meanwhile the lease expires and another worker takes the job over and writes.
        while context.store.claim(job_id, "successor", 30.0) is None:
            context.store._update(expire)  # again if a heartbeat renewed it in between
        work.append(context.storage.work_dir(job_id, "successor"))
        (work[0] / "mesh.json").write_text("{}")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            progress("matching", 0.5)  # raises once the heartbeat found the lease lost
            time.sleep(0.01)
        raise AssertionError("the lost lease did not stop the registration")

    context.runner = stalled
    assert run_job(job_id, context) == "skipped"
    assert (work[0] / "mesh.json").is_file()
    job = context.store.get(job_id)
    assert job is not None and job.status == JobStatus.running
    assert (job.lease_owner, job.attempts, job.finished) == ("successor", 2, None)


def test_stop_event_gives_the_job_back(context: WorkerContext, pair: Pair) -> None:
    stop = threading.Event()
    context.stop_event = stop

    def until_stopped(reference, moving, points=None, options=None, progress=None):  # noqa: ANN001
        stop.set()
        progress("matching", 0.1)
        raise AssertionError("not stopped")

    context.runner = until_stopped
    job_id = add_job(context, pair)
    assert run_job(job_id, context) == "accepted"
    job = context.store.get(job_id)
    assert job is not None and job.status == JobStatus.accepted and job.attempts == 0


def test_metrics_histogram_is_cumulative() -> None:
    metrics = Metrics()
    metrics.track_store(lambda: {s: 0 for s in JobStatus}, lambda: 3, 2)
    for seconds in (0.05, 0.3, 0.3, 7.0, 5000.0):
        metrics.observe_job("successful", seconds, {"matching": seconds / 2})
    samples = metric_samples(metrics.render().decode())
    bucket = "pwlreg_job_duration_seconds_bucket"
    assert one(samples, bucket, status="successful", le="0.1") == 1
    assert one(samples, bucket, status="successful", le="0.5") == 3
    assert one(samples, bucket, status="successful", le="10.0") == 4
    assert one(samples, bucket, status="successful", le="1800.0") == 4
    assert one(samples, bucket, status="successful", le="+Inf") == 5
    assert one(samples, "pwlreg_job_duration_seconds_count", status="successful") == 5
    assert one(samples, "pwlreg_stage_duration_seconds_count", stage="matching") == 5
    assert one(samples, "pwlreg_queue_depth") == 3
    assert one(samples, "pwlreg_jobs", status="accepted") == 0
    # A second instance has its own registry: nothing shared, nothing clashes.
    assert one(metric_samples(Metrics().render().decode()),
               "pwlreg_job_duration_seconds_count", status="successful") == 0


def test_stage_timings_from_the_registration() -> None:
    timings = {"matching_s": 1.0, "triangulation_s": 0.5, "optimization_s": 2.0,
               "rendering_s": 0.25, "quality_s": 0.125, "total_s": 3.875}
    assert stage_timings(timings) == {"matching": 1.0, "triangulating": 0.5, "optimizing": 2.0,
                                      "rendering": 0.375}
    assert stage_timings(None) is None and stage_timings({}) is None


def test_json_log_records_carry_the_job() -> None:
    record = logging.LogRecord("pwlreg.service.worker", logging.INFO, __file__, 1, "job %s: %s",
                               ("j1", 'said "hi"\nthen left'), None)
    record.job_id, record.client = "j1", "alice"
    doc = json.loads(JsonFormatter().format(record))
    assert doc["message"] == 'job j1: said "hi"\nthen left'
    assert (doc["level"], doc["logger"], doc["job_id"], doc["client"]) == (
        "INFO", "pwlreg.service.worker", "j1", "alice")
    assert doc["time"].endswith("Z")
    plain = logging.LogRecord("x", logging.WARNING, __file__, 1, "no job", None, None)
    assert "job_id" not in json.loads(JsonFormatter().format(plain))


def test_storage_sweep_removes_leftovers_only(tmp_path: Path) -> None:
    storage = LocalStorage(tmp_path)
    storage.prepare()
    stale = storage.new_staging()
    orphan = storage.jobs / "orphan"
    orphan.mkdir()
    known = storage.jobs / "known"
    known.mkdir()
    old = time.time() - 7200
    for path in (stale, orphan, known):
        os.utime(path, (old, old))
    fresh = storage.new_staging()
    removed = storage.sweep(lambda ids: {"known"} & set(ids), older_than=3600)
    assert removed == 2
    assert not stale.exists() and not orphan.exists()
    assert known.exists() and fresh.exists()


def test_a_long_stage_without_reports_keeps_its_lease(context: WorkerContext, pair: Pair) -> None:
    lease = context.settings.lease_seconds

    def quiet(reference, moving, points=None, options=None, progress=None):  # noqa: ANN001
        time.sleep(2.5 * lease)  # no progress report for 2.5 leases
        return register(reference, moving, points=points, options=options, progress=progress)

    context.runner = quiet
    job_id = add_job(context, pair)
    janitor = Janitor(context.settings, context.store, context.storage, RecordingQueue())  # type: ignore[arg-type]
    outcome: list[str] = []
    thread = threading.Thread(target=lambda: outcome.append(run_job(job_id, context)))
    thread.start()
    requeued = []
    while thread.is_alive():
        requeued += janitor.recover()[0]
        time.sleep(0.1)
    thread.join()
    assert requeued == [] and outcome == ["successful"]
    job = context.store.get(job_id)
    assert job is not None and job.attempts == 1


def test_a_stuck_registration_is_failed_and_its_process_ended(
    context: WorkerContext, pair: Pair
) -> None:
    context.settings = context.settings.model_copy(
        update={"job_time_limit": 0.3, "lease_seconds": 0.4}
    )
    aborted = threading.Event()
    context.abort = aborted.set

    def stuck(reference, moving, points=None, options=None, progress=None):  # noqa: ANN001
        aborted.wait(10)  # never reports; "ends" when the worker process would be ended
        return None

    context.runner = stuck
    job_id = add_job(context, pair)
    run_job(job_id, context)
    assert aborted.is_set()
    job = context.store.get(job_id)
    assert job is not None and job.status == JobStatus.failed
    assert job.error is not None and job.error["type"].endswith("time-limit-exceeded")
    assert "did not stop" in job.message


def test_worker_threads_change_the_speed_not_the_results(tmp_path: Path, pair: Pair) -> None:
    # More threads decode the two images at once and compress the PNG in pieces.
    results = []
    for threads in (1, 2):
        settings = Settings(_env_file=None, data_dir=tmp_path / str(threads),  # type: ignore[call-arg]
                            worker_threads=threads)
        ctx = WorkerContext.from_settings(settings)
        ctx.storage.prepare()
        ctx.store.create_schema()
        job_id = add_job(ctx, pair)
        assert run_job(job_id, ctx) == "successful"
        mesh = json.loads(ctx.storage.result_path(job_id, "mesh").read_text())  # type: ignore[union-attr]
        png = ctx.storage.result_path(job_id, "registered").read_bytes()  # type: ignore[union-attr]
        results.append((mesh, cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)))
    (mesh1, image1), (mesh2, image2) = results
    assert mesh1["final_triangles"] == mesh2["final_triangles"] and mesh1["swaps"] == mesh2["swaps"]
    np.testing.assert_array_equal(image1, image2)
    assert image1.shape[:2] == (240, 320) and image1[..., 3].any()


def test_jobs_queued_by_the_previous_version_still_run(context: WorkerContext, pair: Pair) -> None:
    # Up to 2026-11-22 the API stored the decoded images (<name>.npy) instead of the uploads.
    job_id = add_job(context, pair)
    inputs = context.storage.jobs / job_id / "inputs"
    for name, data in (("reference", pair.reference_png), ("moving", pair.moving_png)):
        np.save(inputs / f"{name}.npy", cv2.imdecode(np.frombuffer(data, np.uint8),
                                                      cv2.IMREAD_UNCHANGED))
        (inputs / name).unlink()
    assert run_job(job_id, context) == "successful"
    job = context.store.get(job_id)
    assert job is not None and job.timings is not None  # seconds per stage, for the metrics
    assert set(job.timings) == {"matching", "triangulating", "optimizing", "rendering"}
