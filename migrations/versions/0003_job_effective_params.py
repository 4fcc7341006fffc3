"""Jobs keep every parameter in effect (``job.effective_params``) so results replay exactly.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22 01:40:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | Sequence[str] | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Add the nullable ``effective_params`` column (JSON object)."""
    with op.batch_alter_table("job") as batch:
        batch.add_column(sa.Column("effective_params", sa.JSON(), nullable=True))


def downgrade() -> None:
    """Drop ``effective_params``."""
    with op.batch_alter_table("job") as batch:
        batch.drop_column("effective_params")
