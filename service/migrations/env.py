"""Alembic environment: runs the revisions over the connection the store passes in
(``config.attributes["connection"]``), or over the database of the ``PWLREG_*`` settings when
started by the ``alembic`` command."""

from __future__ import annotations

from alembic import context

from pwlreg.service.store import Base, make_engine


def _run(connection) -> None:  # noqa: ANN001 (a SQLAlchemy connection)
    # Batch mode: SQLite alters a table by copying it, PostgreSQL with ALTER TABLE.
    context.configure(connection=connection, target_metadata=Base.metadata,
                      render_as_batch=True, compare_type=True)
    with context.begin_transaction():
        context.run_migrations()


connection = context.config.attributes.get("connection")
if connection is not None:
    _run(connection)
else:
    from pwlreg.service.settings import Settings

    engine = make_engine(Settings().resolved_database_url)
    with engine.begin() as own:
        _run(own)
    engine.dispose()
