"""initial schema: tenants, api keys, projects, images, POS, jobs, stages, artifacts, webhooks

Revision ID: 0001
Revises:
Create Date: 2026-11-22
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0001"
down_revision: str | Sequence[str] | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")
TS = sa.DateTime(timezone=True)


def _id() -> sa.Column:
    return sa.Column("id", sa.String(36), nullable=False)


def _fk_col(name: str, nullable: bool = False) -> sa.Column:
    return sa.Column(name, sa.String(36), nullable=nullable)


def _fk(table: str, col: str, target: str) -> sa.ForeignKeyConstraint:
    return sa.ForeignKeyConstraint(
        [col], [f"{target}.id"], name=op.f(f"fk_{table}_{col}_{target}"), ondelete="CASCADE"
    )


def _status_check(table: str, name: str, values: tuple[str, ...]) -> sa.CheckConstraint:
    listed = ", ".join(f"'{v}'" for v in values)
    return sa.CheckConstraint(f"status IN ({listed})", name=op.f(f"ck_{table}_{name}"))


def upgrade() -> None:
    op.create_table(
        "tenants",
        _id(),
        sa.Column("name", sa.String(200), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_tenants")),
        sa.UniqueConstraint("name", name=op.f("uq_tenants_name")),
    )
    op.create_table(
        "api_keys",
        _id(),
        _fk_col("tenant_id"),
        sa.Column("name", sa.String(200), nullable=False),
        sa.Column("prefix", sa.String(16), nullable=False),
        sa.Column("key_hash", sa.String(64), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.Column("revoked_at", TS, nullable=True),
        _fk("api_keys", "tenant_id", "tenants"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_api_keys")),
        sa.UniqueConstraint("key_hash", name=op.f("uq_api_keys_key_hash")),
    )
    op.create_index(op.f("ix_api_keys_prefix"), "api_keys", ["prefix"])
    op.create_index(op.f("ix_api_keys_tenant_id"), "api_keys", ["tenant_id"])

    op.create_table(
        "projects",
        _id(),
        _fk_col("tenant_id"),
        sa.Column("name", sa.String(200), nullable=False),
        sa.Column("description", sa.Text(), nullable=True),
        sa.Column("crs", sa.String(64), nullable=True),
        sa.Column("origin_lat", sa.Double(), nullable=True),
        sa.Column("origin_lon", sa.Double(), nullable=True),
        sa.Column("origin_h", sa.Double(), nullable=True),
        sa.Column("created_at", TS, nullable=False),
        _fk("projects", "tenant_id", "tenants"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_projects")),
        sa.UniqueConstraint("tenant_id", "name", name="uq_projects_tenant_name"),
    )

    op.create_table(
        "webhooks",
        _id(),
        _fk_col("tenant_id"),
        sa.Column("url", sa.String(2048), nullable=False),
        sa.Column("secret", sa.String(255), nullable=False),
        sa.Column("events", JSON, nullable=False),
        sa.Column("active", sa.Boolean(), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        _fk("webhooks", "tenant_id", "tenants"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_webhooks")),
    )
    op.create_index(op.f("ix_webhooks_tenant_id"), "webhooks", ["tenant_id"])

    op.create_table(
        "images",
        _id(),
        _fk_col("project_id"),
        sa.Column("name", sa.String(512), nullable=False),
        sa.Column("image_set", sa.String(16), nullable=False),
        sa.Column("sha256", sa.String(64), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("width", sa.Integer(), nullable=True),
        sa.Column("height", sa.Integer(), nullable=True),
        sa.Column("storage_key", sa.String(1024), nullable=False),
        sa.Column("metadata", JSON, nullable=True),
        sa.Column("created_at", TS, nullable=False),
        sa.CheckConstraint("image_set IN ('aerial', 'ground')", name=op.f("ck_images_image_set")),
        _fk("images", "project_id", "projects"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_images")),
        sa.UniqueConstraint("project_id", "name", name="uq_images_project_name"),
    )
    op.create_index("ix_images_project_set", "images", ["project_id", "image_set"])

    op.create_table(
        "pos_records",
        _id(),
        _fk_col("project_id"),
        sa.Column("image_name", sa.String(512), nullable=False),
        sa.Column("lat", sa.Double(), nullable=False),
        sa.Column("lon", sa.Double(), nullable=False),
        sa.Column("h", sa.Double(), nullable=False),
        sa.Column("attitude", JSON, nullable=True),
        sa.Column("std_xy", sa.Double(), nullable=True),
        sa.Column("std_z", sa.Double(), nullable=True),
        sa.Column("std_att", sa.Double(), nullable=True),
        sa.Column("source_format", sa.String(32), nullable=True),
        sa.Column("created_at", TS, nullable=False),
        _fk("pos_records", "project_id", "projects"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_pos_records")),
        sa.UniqueConstraint("project_id", "image_name", name="uq_pos_records_project_image"),
    )

    op.create_table(
        "jobs",
        _id(),
        _fk_col("project_id"),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("current_stage", sa.String(64), nullable=True),
        sa.Column("progress", sa.Double(), nullable=False),
        sa.Column("options", JSON, nullable=False),
        sa.Column("timings", JSON, nullable=False),
        sa.Column("metrics", JSON, nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("attempt", sa.Integer(), nullable=False),
        sa.Column("celery_root_id", sa.String(255), nullable=True),
        sa.Column("created_at", TS, nullable=False),
        sa.Column("started_at", TS, nullable=True),
        sa.Column("finished_at", TS, nullable=True),
        sa.CheckConstraint("progress >= 0 AND progress <= 1", name=op.f("ck_jobs_progress_range")),
        _status_check("jobs", "job_status", ("queued", "running", "succeeded", "failed", "cancelled")),
        _fk("jobs", "project_id", "projects"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_jobs")),
    )
    op.create_index("ix_jobs_project_created", "jobs", ["project_id", "created_at"])
    op.create_index(op.f("ix_jobs_status"), "jobs", ["status"])

    op.create_table(
        "stage_runs",
        _id(),
        _fk_col("job_id"),
        sa.Column("stage", sa.String(64), nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("attempt", sa.Integer(), nullable=False),
        sa.Column("worker", sa.String(255), nullable=True),
        sa.Column("started_at", TS, nullable=False),
        sa.Column("finished_at", TS, nullable=True),
        sa.Column("duration_s", sa.Double(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("output_key", sa.String(1024), nullable=True),
        _status_check(
            "stage_runs", "stage_status", ("running", "succeeded", "failed", "skipped", "cancelled")
        ),
        _fk("stage_runs", "job_id", "jobs"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_stage_runs")),
    )
    op.create_index("ix_stage_runs_job_stage", "stage_runs", ["job_id", "stage"])

    op.create_table(
        "artifacts",
        _id(),
        _fk_col("job_id"),
        sa.Column("kind", sa.String(64), nullable=False),
        sa.Column("name", sa.String(512), nullable=False),
        sa.Column("storage_key", sa.String(1024), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=True),
        sa.Column("sha256", sa.String(64), nullable=True),
        sa.Column("content_type", sa.String(255), nullable=True),
        sa.Column("created_at", TS, nullable=False),
        _fk("artifacts", "job_id", "jobs"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_artifacts")),
        sa.UniqueConstraint("job_id", "name", name="uq_artifacts_job_name"),
    )

    op.create_table(
        "webhook_deliveries",
        _id(),
        _fk_col("webhook_id"),
        _fk_col("job_id", nullable=True),
        sa.Column("event", sa.String(64), nullable=False),
        sa.Column("payload", JSON, nullable=False),
        sa.Column("status", sa.String(16), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("next_attempt_at", TS, nullable=True),
        sa.Column("last_error", sa.Text(), nullable=True),
        sa.Column("created_at", TS, nullable=False),
        _status_check("webhook_deliveries", "delivery_status", ("pending", "delivered", "failed")),
        _fk("webhook_deliveries", "job_id", "jobs"),
        _fk("webhook_deliveries", "webhook_id", "webhooks"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_webhook_deliveries")),
    )
    op.create_index("ix_webhook_deliveries_due", "webhook_deliveries", ["status", "next_attempt_at"])
    op.create_index(op.f("ix_webhook_deliveries_job_id"), "webhook_deliveries", ["job_id"])
    op.create_index(op.f("ix_webhook_deliveries_webhook_id"), "webhook_deliveries", ["webhook_id"])


def downgrade() -> None:
    # children first; dropping a table drops its indexes and constraints
    for table in (
        "webhook_deliveries",
        "artifacts",
        "stage_runs",
        "jobs",
        "pos_records",
        "images",
        "webhooks",
        "projects",
        "api_keys",
        "tenants",
    ):
        op.drop_table(table)
