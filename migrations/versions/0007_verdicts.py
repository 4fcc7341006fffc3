"""Review verdicts (``job_verdict``, the current one in ``job.verdict``) and the thresholds a
site learned from them (``site.calibration``).

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-02 06:00:00

"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | Sequence[str] | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Add ``site.calibration``, ``job.verdict`` (nullable JSON) and the ``job_verdict`` table."""
    with op.batch_alter_table("site") as batch:
        batch.add_column(sa.Column("calibration", sa.JSON(), nullable=True))
    with op.batch_alter_table("job") as batch:
        batch.add_column(sa.Column("verdict", sa.JSON(), nullable=True))
    op.create_table(
        "job_verdict",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("organisation_id", sa.String(length=32), nullable=False),
        sa.Column("site_id", sa.String(length=32), nullable=False),
        sa.Column("job_id", sa.String(length=32), nullable=False),
        sa.Column("verdict", sa.String(length=16), nullable=False),
        sa.Column("note", sa.Text(), nullable=True),
        sa.Column("token_id", sa.String(length=32), nullable=True),
        sa.Column("token_name", sa.String(length=200), nullable=True),
        sa.Column("role", sa.String(length=16), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["organisation_id"],
            ["organisation.id"],
            name=op.f("fk_job_verdict_organisation_id_organisation"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["site_id"], ["site.id"], name=op.f("fk_job_verdict_site_id_site"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["job_id"], ["job.id"], name=op.f("fk_job_verdict_job_id_job"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_job_verdict")),
    )
    with op.batch_alter_table("job_verdict") as batch:
        batch.create_index("ix_job_verdict_organisation_id", ["organisation_id"])
        batch.create_index("ix_job_verdict_site_id", ["site_id"])
        batch.create_index("ix_job_verdict_job_created", ["job_id", "created_at"])


def downgrade() -> None:
    """Drop ``job_verdict``, ``job.verdict`` and ``site.calibration``."""
    op.drop_table("job_verdict")
    with op.batch_alter_table("job") as batch:
        batch.drop_column("verdict")
    with op.batch_alter_table("site") as batch:
        batch.drop_column("calibration")
