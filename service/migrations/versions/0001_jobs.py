"""The job table of the first release with migrations (what its ``create_schema`` made).

A database made before migrations existed has the table already, perhaps without the columns
and indexes added since (those releases added them at start): the upgrade adds what it lacks.

Revision ID: 0001
Revises:
Create Date: 2026-11-23
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

INDEXES = {
    "ix_jobs_status_created": ["status", "created"],
    "ix_jobs_created": ["created"],
    "ix_jobs_owner_status": ["owner", "status"],
    "ix_jobs_webhook_due": ["webhook_state", "webhook_next"],
}


def _columns() -> list[sa.Column]:
    return [
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("stage", sa.String(16)),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("message", sa.Text()),
        sa.Column("error", sa.JSON()),
        sa.Column("quality", sa.JSON()),
        sa.Column("timings", sa.JSON()),
        sa.Column("options", sa.JSON(), nullable=False),
        sa.Column("has_points", sa.Boolean(), nullable=False),
        sa.Column("idempotency_key", sa.String(255), unique=True),
        sa.Column("request_hash", sa.String(64)),
        sa.Column("owner", sa.String(64)),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("max_attempts", sa.Integer(), nullable=False),
        sa.Column("lease_owner", sa.String(128)),
        sa.Column("lease_expires", sa.DateTime()),
        sa.Column("created", sa.DateTime(), nullable=False),
        sa.Column("updated", sa.DateTime(), nullable=False),
        sa.Column("started", sa.DateTime()),
        sa.Column("finished", sa.DateTime()),
        sa.Column("callback", sa.JSON()),
        sa.Column("webhook_event", sa.String(16)),
        sa.Column("webhook_state", sa.String(16)),
        sa.Column("webhook_attempts", sa.Integer()),
        sa.Column("webhook_next", sa.DateTime()),
        sa.Column("webhook_last", sa.DateTime()),
        sa.Column("webhook_error", sa.Text()),
        sa.Column("webhook_delivery", sa.String(32)),
    ]


def upgrade() -> None:
    inspector = sa.inspect(op.get_bind())
    if "jobs" not in inspector.get_table_names():
        op.create_table("jobs", *_columns())
        present_indexes: set[str] = set()
    else:
        present = {c["name"] for c in inspector.get_columns("jobs")}
        missing = [c for c in _columns() if c.name not in present and c.nullable]
        # The unique constraint goes with the table, not with an added column.
        for column in missing:
            column.unique = None
        if missing:
            with op.batch_alter_table("jobs") as batch:
                for column in missing:
                    batch.add_column(column)
        present_indexes = {i["name"] for i in inspector.get_indexes("jobs")}
    for name, columns in INDEXES.items():
        if name not in present_indexes:
            op.create_index(name, "jobs", columns)


def downgrade() -> None:
    op.drop_table("jobs")
