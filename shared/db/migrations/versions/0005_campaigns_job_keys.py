"""campaigns, jobs.client_key and jobs.campaign_id: client-chosen job keys (a retried submission finds
its job instead of making a second one) and campaigns of many surveys with their status

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-01
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | Sequence[str] | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "campaigns",
        sa.Column("id", sa.String(36), primary_key=True),
        sa.Column(
            "tenant_id",
            sa.String(36),
            sa.ForeignKey("tenants.id", ondelete="CASCADE", name="fk_campaigns_tenant_id_tenants"),
            nullable=False,
        ),
        sa.Column("name", sa.String(200), nullable=False),
        sa.Column("max_concurrent", sa.Integer, nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.UniqueConstraint("tenant_id", "name", name="uq_campaigns_tenant_name"),
    )
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("client_key", sa.String(128), nullable=True))
        batch.add_column(sa.Column("campaign_id", sa.String(36), nullable=True))
        batch.create_foreign_key(
            "fk_jobs_campaign_id_campaigns", "campaigns", ["campaign_id"], ["id"], ondelete="SET NULL"
        )
        batch.create_unique_constraint("uq_jobs_project_client_key", ["project_id", "client_key"])
        batch.create_index("ix_jobs_campaign_id", ["campaign_id"])


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.drop_index("ix_jobs_campaign_id")
        batch.drop_constraint("uq_jobs_project_client_key", type_="unique")
        batch.drop_constraint("fk_jobs_campaign_id_campaigns", type_="foreignkey")
        batch.drop_column("campaign_id")
        batch.drop_column("client_key")
    op.drop_table("campaigns")
