"""Jobs keep their sensor origins, quality warnings and the explanation of their decision.

``job.sensor_origins`` (per side a list of ``{origin, source, confidence}``), ``job.warnings``
(a list of ``{code, message, ...}``) and ``job.explanation`` (structured, with a one-line
``text``): all JSON, null until the job succeeded (and for jobs stored before this revision).

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-02 05:50:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | Sequence[str] | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

COLUMNS = ("sensor_origins", "warnings", "explanation")


def upgrade() -> None:
    """Add the three nullable JSON columns."""
    with op.batch_alter_table("job") as batch:
        for name in COLUMNS:
            batch.add_column(sa.Column(name, sa.JSON(), nullable=True))


def downgrade() -> None:
    """Drop them."""
    with op.batch_alter_table("job") as batch:
        for name in reversed(COLUMNS):
            batch.drop_column(name)
