"""Schedule runs say why nothing was compared (``schedule_run.reason``), and a schedule
remembers the start of its missed spell (``schedule.missed_since``) so that
``schedule.missed`` is published once per spell (issue 31).

Revision ID: 0012
Revises: 0011
Create Date: 2026-12-04 21:30:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0012"
down_revision: str | Sequence[str] | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Add ``schedule_run.reason`` and ``schedule.missed_since`` (both null: nothing known)."""
    with op.batch_alter_table("schedule_run") as batch:
        batch.add_column(sa.Column("reason", sa.Text(), nullable=True))
    with op.batch_alter_table("schedule") as batch:
        batch.add_column(sa.Column("missed_since", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    """Drop ``schedule.missed_since`` and ``schedule_run.reason``."""
    with op.batch_alter_table("schedule") as batch:
        batch.drop_column("missed_since")
    with op.batch_alter_table("schedule_run") as batch:
        batch.drop_column("reason")
