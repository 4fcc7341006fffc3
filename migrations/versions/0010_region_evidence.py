"""Regions say why they are a change (``region.evidence``: seen_empty or surface_moved, and
``region.confidence``), and a job keeps the clusters the other epoch did not cover
(``job.uncertain_regions``, evidence no_coverage) (issue 29).

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-04 21:40:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0010"
down_revision: str | Sequence[str] | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Add the evidence columns (regions stored before: seen_empty, confidence unknown)."""
    with op.batch_alter_table("region") as batch:
        batch.add_column(
            sa.Column("evidence", sa.String(16), nullable=False, server_default="seen_empty")
        )
        batch.add_column(sa.Column("confidence", sa.Float(), nullable=True))
    with op.batch_alter_table("job") as batch:
        batch.add_column(sa.Column("uncertain_regions", sa.JSON(), nullable=True))


def downgrade() -> None:
    """Drop them."""
    with op.batch_alter_table("job") as batch:
        batch.drop_column("uncertain_regions")
    with op.batch_alter_table("region") as batch:
        batch.drop_column("confidence")
        batch.drop_column("evidence")
