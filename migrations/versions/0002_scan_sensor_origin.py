"""Scans remember where their sensor was (``scan.sensor_origin``).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22 01:30:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | Sequence[str] | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Add the nullable ``sensor_origin`` column (JSON list of three floats)."""
    with op.batch_alter_table("scan") as batch:
        batch.add_column(sa.Column("sensor_origin", sa.JSON(), nullable=True))


def downgrade() -> None:
    """Drop ``sensor_origin``."""
    with op.batch_alter_table("scan") as batch:
        batch.drop_column("sensor_origin")
