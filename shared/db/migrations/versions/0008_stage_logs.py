"""jobs.progress_message (what the running stage last reported, sent with its progress events) and
stage_runs.log (the lines the stage logged while it ran, kept for the job's log)

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-05
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | Sequence[str] | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("progress_message", sa.String(500), nullable=True))
    with op.batch_alter_table("stage_runs") as batch:
        batch.add_column(sa.Column("log", sa.Text(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("stage_runs") as batch:
        batch.drop_column("log")
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("progress_message")
