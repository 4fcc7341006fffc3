"""Scans keep the size of their cached k-NN geometry (``scan.geometry_cache_bytes``), which the
organisation's stored-bytes quota counts (issue 18).

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-02 06:00:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | Sequence[str] | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Add ``geometry_cache_bytes`` (0: no cache yet, as for every scan stored before it)."""
    with op.batch_alter_table("scan") as batch:
        batch.add_column(
            sa.Column("geometry_cache_bytes", sa.Integer(), nullable=False, server_default="0")
        )


def downgrade() -> None:
    """Drop ``geometry_cache_bytes``."""
    with op.batch_alter_table("scan") as batch:
        batch.drop_column("geometry_cache_bytes")
