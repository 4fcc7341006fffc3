"""Jobs keep the id of the API request that created them (``job.request_id``) for the logs;
an index on ``job.finished_at`` bounds the metrics' duration histogram to the last day's jobs.

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-02 03:30:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | Sequence[str] | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Add the nullable ``request_id`` column (jobs created before it have none) and the index."""
    with op.batch_alter_table("job") as batch:
        batch.add_column(sa.Column("request_id", sa.String(length=64), nullable=True))
        batch.create_index("ix_job_finished_at", ["finished_at"])


def downgrade() -> None:
    """Drop the index and ``request_id``."""
    with op.batch_alter_table("job") as batch:
        batch.drop_index("ix_job_finished_at")
        batch.drop_column("request_id")
