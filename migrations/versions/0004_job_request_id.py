"""Jobs keep the id of the API request that created them (``job.request_id``) for the logs.

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
    """Add the nullable ``request_id`` column (jobs created before it have none)."""
    with op.batch_alter_table("job") as batch:
        batch.add_column(sa.Column("request_id", sa.String(length=64), nullable=True))


def downgrade() -> None:
    """Drop ``request_id``."""
    with op.batch_alter_table("job") as batch:
        batch.drop_column("request_id")
