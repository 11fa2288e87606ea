"""The job store on SQLite and PostgreSQL: Alembic migrations (a new database, one made by the
previous release, one from a newer release), the claim rules that make redelivery safe, and the
dispatch of accepted jobs to a real Redis broker."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest
import redis
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import text, update

from pwlreg.service.cli import main
from pwlreg.service.queue import CeleryQueue
from pwlreg.service.settings import Settings
from pwlreg.service.store import (
    Base,
    JobRow,
    JobStatus,
    JobStore,
    SchemaBehind,
    SchemaError,
    alembic_config,
    utcnow,
)
from tests.service.scaleout import broker, database  # noqa: F401 (fixtures)

PREVIOUS = json.loads((Path(__file__).parent / "fixtures" / "schema_before_migrations.json")
                      .read_text())


@pytest.fixture(params=["sqlite", "postgresql"])
def url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A new empty database of each kind."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'jobs.db'}"
    return request.getfixturevalue("database")


@pytest.fixture()
def store(url: str) -> Iterator[JobStore]:
    store = JobStore.from_url(url)
    yield store
    store.dispose()


@pytest.fixture()
def root_logging() -> Iterator[None]:
    """Give back the root logger's handlers that ``pwlreg worker`` replaces in this process."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def _drift(store: JobStore) -> list:
    """Differences between the database's schema and the models (empty: they agree)."""
    with store.engine.connect() as connection:
        return compare_metadata(MigrationContext.configure(connection), Base.metadata)


def test_a_new_database_gets_the_schema_of_the_models(store: JobStore) -> None:
    store.create_schema()
    store.create_schema()  # at the newest revision: nothing to do
    current, head = store.schema_revision()
    assert current == head is not None
    assert _drift(store) == []
    store.check_schema()
    # Every revision goes down and up again.
    with store.engine.begin() as connection:
        command.downgrade(alembic_config(connection), "base")
    assert store.schema_revision()[0] is None
    with pytest.raises(SchemaBehind, match="upgrades it when it starts"):
        store.check_schema()
    store.create_schema()
    assert _drift(store) == []


def test_a_database_of_the_previous_release_is_migrated(store: JobStore) -> None:
    # The table exactly as the previous release's create_schema() made it, with its jobs.
    with store.engine.begin() as connection:
        for statement in PREVIOUS[store.engine.dialect.name]:
            connection.exec_driver_sql(statement)
        connection.execute(text(
            "INSERT INTO jobs (id, status, progress, options, has_points, attempts, "
            "max_attempts, created, updated, lease_owner, lease_expires, quality, callback, "
            "webhook_state, owner) VALUES "
            "('done', 'successful', 100, '{\"bins\": 32}', true, 1, 3, '2026-11-20 10:00:00', "
            "'2026-11-20 10:01:00', NULL, NULL, '{\"verdict\": \"good\"}', "
            "'{\"success_uri\": \"https://example.org/h\"}', 'delivered', 'alice'), "
            "('waiting', 'accepted', 0, '{}', false, 0, 3, '2026-11-20 10:02:00', "
            "'2026-11-20 10:02:00', NULL, NULL, NULL, NULL, NULL, NULL), "
            "('orphan', 'running', 40, '{}', false, 1, 3, '2026-11-20 10:03:00', "
            "'2026-11-20 10:03:00', 'old-worker', '2026-11-20 10:04:00', NULL, NULL, NULL, NULL)"
        ))
    store.create_schema()
    assert store.schema_revision()[0] == store.schema_revision()[1]
    assert _drift(store) == []
    done = store.get("done")
    assert done is not None and done.status == JobStatus.successful
    assert done.options == {"bins": 32} and done.quality == {"verdict": "good"}
    assert done.callback == {"success_uri": "https://example.org/h"} and done.owner == "alice"
    assert done.created.isoformat() == "2026-11-20T10:00:00+00:00" and done.dispatched is None
    # The jobs of the previous release go on: the waiting one is dispatched and claimed, the
    # one whose worker died is requeued.
    assert store.undispatched(10, utcnow()) == ["waiting"]
    assert store.claim("waiting", "w", 30) is not None
    assert store.recover_expired(lambda message: {"detail": message}) == (["orphan"], [])
    assert [j.id for j in store.list(owner="alice")[0]] == ["done"]


def test_a_database_made_before_some_columns_gets_them(tmp_path: Path) -> None:
    # Releases before migrations added columns at start; a database they left behind lacks the
    # later ones, and the first revision adds them.
    store = JobStore.from_url(f"sqlite:///{tmp_path / 'old.db'}")
    with store.engine.begin() as connection:
        connection.exec_driver_sql(
            "CREATE TABLE jobs (id VARCHAR(32) NOT NULL PRIMARY KEY, status VARCHAR(16) NOT "
            "NULL, stage VARCHAR(16), progress FLOAT NOT NULL, message TEXT, error JSON, options "
            "JSON NOT NULL, has_points BOOLEAN NOT NULL, idempotency_key VARCHAR(255), "
            "request_hash VARCHAR(64), attempts INTEGER NOT NULL, max_attempts INTEGER NOT NULL, "
            "lease_owner VARCHAR(128), lease_expires DATETIME, created DATETIME NOT NULL, "
            "updated DATETIME NOT NULL, started DATETIME, finished DATETIME, "
            "UNIQUE (idempotency_key))"
        )
        connection.exec_driver_sql(
            "INSERT INTO jobs VALUES ('old', 'failed', NULL, 0, 'x', NULL, '{}', 0, NULL, NULL, "
            "1, 3, NULL, NULL, '2026-11-01 00:00:00', '2026-11-01 00:00:00', NULL, NULL)"
        )
    try:
        store.create_schema()
        assert _drift(store) == []
        old = store.get("old")
        assert old is not None and old.owner is None and old.quality is None
    finally:
        store.dispose()


def test_a_database_of_a_newer_release_is_refused(
    store: JobStore, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
    root_logging: None, tmp_path: Path,
) -> None:
    store.create_schema()
    with store.engine.begin() as connection:
        connection.execute(text("UPDATE alembic_version SET version_num = '9999'"))
    with pytest.raises(SchemaError, match="'9999', which this release of pwlreg does not know"):
        store.create_schema()
    with pytest.raises(SchemaError) as raised:
        store.check_schema()
    assert not isinstance(raised.value, SchemaBehind)
    # A worker refuses at once, in one line.
    monkeypatch.setenv("PWLREG_DATABASE_URL", store.engine.url.render_as_string(False))
    monkeypatch.setenv("PWLREG_BROKER_URL", "redis://127.0.0.1:1/0")
    monkeypatch.setenv("PWLREG_DATA_DIR", str(tmp_path / "data"))
    t0 = time.monotonic()
    assert main(["worker"]) == 2
    assert time.monotonic() - t0 < 10
    message = capsys.readouterr().err
    assert "pwlreg worker: error:" in message and "'9999'" in message


def test_pwlreg_worker_needs_a_broker(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path,
    root_logging: None,
) -> None:
    monkeypatch.delenv("PWLREG_BROKER_URL", raising=False)
    monkeypatch.setenv("PWLREG_DATA_DIR", str(tmp_path))
    assert main(["worker"]) == 2
    assert "PWLREG_BROKER_URL" in capsys.readouterr().err


def _job(store: JobStore, job_id: str, max_attempts: int = 3) -> None:
    store.create(job_id, {}, False, max_attempts)


def test_claims_decide_who_runs_a_job(store: JobStore) -> None:
    store.create_schema()
    _job(store, "j")
    winners = []
    barrier = threading.Barrier(4)

    def claim(owner: str) -> None:
        barrier.wait()
        if store.claim("j", owner, 30) is not None:
            winners.append(owner)

    threads = [threading.Thread(target=claim, args=(f"w{i}",)) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(winners) == 1
    # A delivery while the lease is alive is refused; once it expired (the worker died), the
    # next delivery takes the job over with one more attempt ...
    assert store.claim("j", "late", 30) is None
    expire = update(JobRow).where(JobRow.id == "j").values(
        lease_expires=utcnow() - timedelta(seconds=1))
    store._update(expire)
    taken = store.claim("j", "next", 30)
    assert taken is not None and taken.attempts == 2 and taken.lease_owner == "next"
    assert not store.renew("j", winners[0], 30)  # the first worker, if alive, stops
    # ... until the attempts are used up: then only the maintenance pass fails it.
    store._update(update(JobRow).where(JobRow.id == "j").values(attempts=3))
    store._update(expire)
    assert store.claim("j", "again", 30) is None
    assert store.recover_expired(lambda message: {"detail": message}) == ([], ["j"])
    assert store.get("j").status == JobStatus.failed  # type: ignore[union-attr]


def test_each_job_is_dispatched_once(store: JobStore) -> None:
    store.create_schema()
    for i in range(5):
        _job(store, f"j{i}")
    horizon = utcnow() - timedelta(hours=1)
    assert store.undispatched(10, horizon) == [f"j{i}" for i in range(5)]
    marked = []
    barrier = threading.Barrier(3)

    def mark(api: int) -> None:
        barrier.wait()
        marked.extend((api, i) for i in range(5) if store.mark_dispatched(f"j{i}", horizon))

    threads = [threading.Thread(target=mark, args=(api,)) for api in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(i for _, i in marked) == list(range(5))  # each by one API process only
    assert store.undispatched(10, horizon) == []
    store.unmark_dispatched("j3")  # its message could not be sent
    assert store.undispatched(10, horizon) == ["j3"]
    # A message sent before the horizon may be lost: sent again.
    assert store.undispatched(10, utcnow() + timedelta(seconds=1)) == [f"j{i}" for i in range(5)]


def test_the_celery_queue_sends_every_accepted_job(
    database: str, broker: dict[str, str], tmp_path: Path  # noqa: F811
) -> None:
    settings = Settings(_env_file=None, data_dir=tmp_path, database_url=database,  # type: ignore[call-arg]
                        queue="celery", broker_url=broker["PWLREG_BROKER_URL"],
                        broker_queue=broker["PWLREG_BROKER_QUEUE"])
    store = JobStore.from_url(database)
    store.create_schema()
    ended: list[str] = []
    queue = CeleryQueue(settings, store, ended.append, poll_interval=0.1)
    client = redis.Redis.from_url(settings.broker_url)  # type: ignore[arg-type]
    try:
        _job(store, "before")  # accepted while no API ran
        queue.start()
        _job(store, "new")
        queue.enqueue("new")
        deadline = time.monotonic() + 10
        while client.llen(settings.broker_queue) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        bodies = [json.loads(m) for m in client.lrange(settings.broker_queue, 0, -1)]
        assert sorted(b["headers"]["argsrepr"] for b in bodies) == ["['before']", "['new']"]
        assert {b["headers"]["task"] for b in bodies} == {"pwlreg.run_job"}
        assert queue.is_ready() and queue.depth() == 2
        time.sleep(0.3)
        assert client.llen(settings.broker_queue) == 2  # sent once each
        # The end of a job it sent is noticed (metrics, webhooks).
        store.dismiss("new")
        deadline = time.monotonic() + 5
        while not ended and time.monotonic() < deadline:
            time.sleep(0.05)
        assert ended == ["new"]
    finally:
        queue.stop()
        client.close()
        store.dispose()


def test_a_job_waits_while_the_broker_is_down(
    database: str, tmp_path: Path, caplog: pytest.LogCaptureFixture  # noqa: F811
) -> None:
    settings = Settings(_env_file=None, data_dir=tmp_path, database_url=database,  # type: ignore[call-arg]
                        queue="celery", broker_url="redis://127.0.0.1:1/0")
    store = JobStore.from_url(database)
    store.create_schema()
    queue = CeleryQueue(settings, store, poll_interval=0.1)
    try:
        queue.start()
        _job(store, "j")
        queue.enqueue("j")
        deadline = time.monotonic() + 15
        while "not sent to the broker" not in caplog.text and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(0.5)  # more passes fail
        assert "job j: not sent to the broker" in caplog.text
        assert caplog.text.count("not sent to the broker") == 1  # once per outage
        assert not queue.is_ready()
        queue.stop()
        assert store.get("j").dispatched is None  # type: ignore[union-attr]
        assert store.undispatched(10, utcnow()) == ["j"]  # sent once the broker is back
    finally:
        queue.stop()
        store.dispose()
