"""The tiles of a job localised on several workers (``job_tile``, issue 30's fan-out).

Revision ID: 0013
Revises: 0012
Create Date: 2026-12-05 00:30:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0013"
down_revision: str | Sequence[str] | None = "0012"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Create ``job_tile``."""
    op.create_table(
        "job_tile",
        sa.Column("job_id", sa.String(32), nullable=False),
        sa.Column("tile_index", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("lease_owner", sa.String(64), nullable=True),
        sa.Column("lease_expires_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("result_path", sa.String(500), nullable=True),
        sa.Column("points", sa.Integer(), nullable=False),
        sa.Column("seconds", sa.Float(), nullable=True),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(
            ["job_id"], ["job.id"], name="fk_job_tile_job_id_job", ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("job_id", "tile_index", name="pk_job_tile"),
    )
    op.create_index("ix_job_tile_job_status", "job_tile", ["job_id", "status"])


def downgrade() -> None:
    """Drop ``job_tile``."""
    op.drop_table("job_tile")
