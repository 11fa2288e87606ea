"""Alembic migrations of the job table (SQLite and PostgreSQL alike).

:meth:`pwlreg.service.store.JobStore.create_schema` runs them at the start of the service. To add
a revision after changing :class:`~pwlreg.service.store.JobRow`, from the repository root::

    PWLREG_DATABASE_URL=sqlite:///scratch.db alembic -c service/migrations/alembic.ini upgrade head
    PWLREG_DATABASE_URL=sqlite:///scratch.db alembic -c service/migrations/alembic.ini \\
        revision --autogenerate -m "what changes"

then read the generated file: a revision must work on both databases.
"""
