"""A streamed job's crops pass split by cloud (``job_crop_pass``, issue 30's fan-out).

Revision ID: 0014
Revises: 0013
Create Date: 2026-12-05 20:00:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0014"
down_revision: str | Sequence[str] | None = "0013"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Create ``job_crop_pass``."""
    op.create_table(
        "job_crop_pass",
        sa.Column("job_id", sa.String(32), nullable=False),
        sa.Column("pass_index", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("lease_owner", sa.String(64), nullable=True),
        sa.Column("lease_expires_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("points", sa.Integer(), nullable=False),
        sa.Column("seconds", sa.Float(), nullable=True),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(
            ["job_id"], ["job.id"], name="fk_job_crop_pass_job_id_job", ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("job_id", "pass_index", name="pk_job_crop_pass"),
    )
    op.create_index("ix_job_crop_pass_job_status", "job_crop_pass", ["job_id", "status"])


def downgrade() -> None:
    """Drop ``job_crop_pass``."""
    op.drop_table("job_crop_pass")
