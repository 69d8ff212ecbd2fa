"""ORM models of the service state, portable between PostgreSQL and SQLite.

Primary keys are UUID strings (36 characters), timestamps are timezone-aware UTC, and every child row
goes away with its parent (ON DELETE CASCADE; SQLite needs `PRAGMA foreign_keys=ON`, see session.py).
"""

from __future__ import annotations

import enum
import uuid
from datetime import UTC, datetime
from typing import Any

import sqlalchemy as sa
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

IMAGE_SETS = ("aerial", "ground")

# JSON everywhere, JSONB on PostgreSQL
JSONType = sa.JSON().with_variant(JSONB(), "postgresql")


def new_id() -> str:
    """A fresh random UUID as a string."""
    return str(uuid.uuid4())


def utcnow() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


class UTCDateTime(sa.TypeDecorator[datetime]):
    """DateTime(timezone=True) that always returns aware UTC datetimes (SQLite stores them naive)."""

    impl = sa.DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: sa.Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime given; use an aware one (e.g. shared.db.models.utcnow())")
        return value.astimezone(UTC)

    def process_result_value(self, value: datetime | None, dialect: sa.Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class JobStatus(enum.StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"


TERMINAL_JOB_STATUSES = frozenset({JobStatus.succeeded, JobStatus.failed, JobStatus.cancelled})


class StageStatus(enum.StrEnum):
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    skipped = "skipped"
    cancelled = "cancelled"


class DeliveryStatus(enum.StrEnum):
    pending = "pending"
    delivered = "delivered"
    failed = "failed"


def _enum(cls: type[enum.Enum], name: str) -> sa.Enum:
    """A VARCHAR + CHECK enum column type (no native PostgreSQL type to migrate)."""
    return sa.Enum(
        cls,
        name=name,
        native_enum=False,
        create_constraint=True,
        length=16,
        values_callable=lambda e: [m.value for m in e],
        validate_strings=True,
    )


NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    metadata = sa.MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map = {datetime: UTCDateTime(), dict[str, Any]: JSONType, list[Any]: JSONType}


def _id() -> Mapped[str]:
    return mapped_column(sa.String(36), primary_key=True, default=new_id)


def _fk(target: str, nullable: bool = False, index: bool = False) -> Mapped[Any]:
    """A cascading foreign key; index it unless a composite index or unique constraint leads with it."""
    return mapped_column(
        sa.String(36), sa.ForeignKey(target, ondelete="CASCADE"), nullable=nullable, index=index
    )


def _children(back_populates: str, **kwargs: Any) -> Any:
    """A one-to-many collection whose rows the database deletes with the parent (ON DELETE CASCADE)."""
    return relationship(
        back_populates=back_populates, cascade="all, delete-orphan", passive_deletes=True, **kwargs
    )


def _created() -> Mapped[datetime]:
    return mapped_column(default=utcnow)


class Tenant(Base):
    __tablename__ = "tenants"

    id: Mapped[str] = _id()
    name: Mapped[str] = mapped_column(sa.String(200), unique=True)
    created_at: Mapped[datetime] = _created()

    api_keys: Mapped[list[ApiKey]] = _children("tenant")
    projects: Mapped[list[Project]] = _children("tenant")
    webhooks: Mapped[list[Webhook]] = _children("tenant")
    campaigns: Mapped[list[Campaign]] = _children("tenant")


class ApiKey(Base):
    """An API key; only its hash is stored, the prefix identifies it in listings and logs."""

    __tablename__ = "api_keys"

    id: Mapped[str] = _id()
    tenant_id: Mapped[str] = _fk("tenants.id", index=True)
    name: Mapped[str] = mapped_column(sa.String(200))
    prefix: Mapped[str] = mapped_column(sa.String(16), index=True)
    key_hash: Mapped[str] = mapped_column(sa.String(64), unique=True)
    created_at: Mapped[datetime] = _created()
    revoked_at: Mapped[datetime | None]

    tenant: Mapped[Tenant] = relationship(back_populates="api_keys")


class Project(Base):
    __tablename__ = "projects"
    __table_args__ = (sa.UniqueConstraint("tenant_id", "name", name="uq_projects_tenant_name"),)

    id: Mapped[str] = _id()
    tenant_id: Mapped[str] = _fk("tenants.id")
    name: Mapped[str] = mapped_column(sa.String(200))
    description: Mapped[str | None] = mapped_column(sa.Text)
    crs: Mapped[str | None] = mapped_column(sa.String(64))
    origin_lat: Mapped[float | None]
    origin_lon: Mapped[float | None]
    origin_h: Mapped[float | None]
    created_at: Mapped[datetime] = _created()

    tenant: Mapped[Tenant] = relationship(back_populates="projects")
    images: Mapped[list[Image]] = _children("project")
    pos_records: Mapped[list[PosRecordRow]] = _children("project")
    jobs: Mapped[list[Job]] = _children("project")
    uploads: Mapped[list[Upload]] = _children("project")


class Campaign(Base):
    """A batch of surveys submitted together: one job per survey (jobs.campaign_id), at most
    max_concurrent of them queued or running at once (the submitting client keeps to it)."""

    __tablename__ = "campaigns"
    __table_args__ = (sa.UniqueConstraint("tenant_id", "name", name="uq_campaigns_tenant_name"),)

    id: Mapped[str] = _id()
    tenant_id: Mapped[str] = _fk("tenants.id")
    name: Mapped[str] = mapped_column(sa.String(200))
    max_concurrent: Mapped[int] = mapped_column(default=2)
    created_at: Mapped[datetime] = _created()

    tenant: Mapped[Tenant] = relationship(back_populates="campaigns")
    jobs: Mapped[list[Job]] = relationship(back_populates="campaign", passive_deletes=True)


class Image(Base):
    """An uploaded image; `name` follows docs/formats.md (`aerial/A0001.jpg`)."""

    __tablename__ = "images"
    __table_args__ = (
        sa.UniqueConstraint("project_id", "name", name="uq_images_project_name"),
        sa.CheckConstraint("image_set IN ('aerial', 'ground')", name="image_set"),
        sa.Index("ix_images_project_set", "project_id", "image_set"),
    )

    id: Mapped[str] = _id()
    project_id: Mapped[str] = _fk("projects.id")
    name: Mapped[str] = mapped_column(sa.String(512))
    image_set: Mapped[str] = mapped_column(sa.String(16))
    sha256: Mapped[str] = mapped_column(sa.String(64))
    size_bytes: Mapped[int] = mapped_column(sa.BigInteger)
    width: Mapped[int | None]
    height: Mapped[int | None]
    storage_key: Mapped[str] = mapped_column(sa.String(1024))
    meta: Mapped[dict[str, Any] | None] = mapped_column("metadata")
    created_at: Mapped[datetime] = _created()

    project: Mapped[Project] = relationship(back_populates="images")


class Upload(Base):
    """An unfinished client-driven multipart upload of one image (api/routes/uploads.py). One per image
    name and project: the unique constraint makes "none in progress" and the start one atomic step."""

    __tablename__ = "uploads"
    __table_args__ = (sa.UniqueConstraint("project_id", "name", name="uq_uploads_project_name"),)

    id: Mapped[str] = _id()
    project_id: Mapped[str] = _fk("projects.id")
    name: Mapped[str] = mapped_column(sa.String(512))  # the image name, aerial/A0001.jpg
    storage_key: Mapped[str] = mapped_column(sa.String(1024))  # where the parts are assembled
    storage_upload_id: Mapped[str] = mapped_column(sa.String(1024))
    size_bytes: Mapped[int] = mapped_column(sa.BigInteger)
    sha256: Mapped[str | None] = mapped_column(sa.String(64))
    part_size: Mapped[int] = mapped_column(sa.BigInteger)
    part_count: Mapped[int]
    created_at: Mapped[datetime] = _created()
    # open (parts arriving), verifying (assembled, checked in the background), rejected (error says why)
    state: Mapped[str] = mapped_column(sa.String(16), default="open", server_default="open")
    error: Mapped[str | None] = mapped_column(sa.Text)
    verify_started_at: Mapped[datetime | None]  # a verifier's claim (api/verify.py)

    project: Mapped[Project] = relationship(back_populates="uploads")


class PosRecordRow(Base):
    """One POS row (services.pos.PosRecord): WGS84 position, optional attitude and accuracies."""

    __tablename__ = "pos_records"
    __table_args__ = (sa.UniqueConstraint("project_id", "image_name", name="uq_pos_records_project_image"),)

    id: Mapped[str] = _id()
    project_id: Mapped[str] = _fk("projects.id")
    image_name: Mapped[str] = mapped_column(sa.String(512))
    lat: Mapped[float]
    lon: Mapped[float]
    h: Mapped[float]
    attitude: Mapped[list[Any] | None]  # R_world_from_cam as a 3x3 nested list, or None
    std_xy: Mapped[float | None]
    std_z: Mapped[float | None]
    std_att: Mapped[float | None]
    source_format: Mapped[str | None] = mapped_column(sa.String(32))
    created_at: Mapped[datetime] = _created()

    project: Mapped[Project] = relationship(back_populates="pos_records")


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = (
        sa.CheckConstraint("progress >= 0 AND progress <= 1", name="progress_range"),
        sa.Index("ix_jobs_project_created", "project_id", "created_at"),
        sa.UniqueConstraint("project_id", "client_key", name="uq_jobs_project_client_key"),
    )

    id: Mapped[str] = _id()
    project_id: Mapped[str] = _fk("projects.id")
    status: Mapped[JobStatus] = mapped_column(
        _enum(JobStatus, "job_status"), default=JobStatus.queued, index=True
    )
    current_stage: Mapped[str | None] = mapped_column(sa.String(64))
    progress: Mapped[float] = mapped_column(default=0.0)
    progress_message: Mapped[str | None] = mapped_column(sa.String(500))  # the running stage's last report
    options: Mapped[dict[str, Any]] = mapped_column(default=dict)
    timings: Mapped[dict[str, Any]] = mapped_column(default=dict)
    metrics: Mapped[dict[str, Any]] = mapped_column(default=dict)
    # what it was created on: {"images": {name: sha256}, "pos_sha256": ...} (crud.input_snapshot)
    inputs: Mapped[dict[str, Any] | None]
    error: Mapped[str | None] = mapped_column(sa.Text)
    attempt: Mapped[int] = mapped_column(default=1)
    # this attempt runs the stages from this one on again even where they are up to date (a forced rerun)
    force_from: Mapped[str | None] = mapped_column(sa.String(64))
    celery_root_id: Mapped[str | None] = mapped_column(sa.String(255))
    # the client's idempotency key: a second creation with it returns this job
    client_key: Mapped[str | None] = mapped_column(sa.String(128))
    campaign_id: Mapped[str | None] = mapped_column(
        sa.String(36), sa.ForeignKey("campaigns.id", ondelete="SET NULL"), index=True
    )
    created_at: Mapped[datetime] = _created()
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]

    project: Mapped[Project] = relationship(back_populates="jobs")
    campaign: Mapped[Campaign | None] = relationship(back_populates="jobs")
    stage_runs: Mapped[list[StageRun]] = _children("job", order_by="StageRun.started_at")
    artifacts: Mapped[list[Artifact]] = _children("job")


class StageRun(Base):
    """One execution of one pipeline stage of a job (a retried stage has several)."""

    __tablename__ = "stage_runs"
    __table_args__ = (sa.Index("ix_stage_runs_job_stage", "job_id", "stage"),)

    id: Mapped[str] = _id()
    job_id: Mapped[str] = _fk("jobs.id")
    stage: Mapped[str] = mapped_column(sa.String(64))
    status: Mapped[StageStatus] = mapped_column(
        _enum(StageStatus, "stage_status"), default=StageStatus.running
    )
    attempt: Mapped[int] = mapped_column(default=1)
    worker: Mapped[str | None] = mapped_column(sa.String(255))
    node: Mapped[str | None] = mapped_column(sa.String(255))  # Celery node name (NAME@HOST) that runs it
    heartbeat_at: Mapped[datetime | None]  # refreshed while a task works on it (workers/tasks.py)
    started_at: Mapped[datetime] = _created()
    finished_at: Mapped[datetime | None]
    duration_s: Mapped[float | None]
    error: Mapped[str | None] = mapped_column(sa.Text)
    output_key: Mapped[str | None] = mapped_column(sa.String(1024))
    log: Mapped[str | None] = mapped_column(
        sa.Text, deferred=True
    )  # lines the stage logged (workers/stagelog.py)

    job: Mapped[Job] = relationship(back_populates="stage_runs")


class Artifact(Base):
    """A stored output of a job (a match file, a model, a report), unique by name per job."""

    __tablename__ = "artifacts"
    __table_args__ = (sa.UniqueConstraint("job_id", "name", name="uq_artifacts_job_name"),)

    id: Mapped[str] = _id()
    job_id: Mapped[str] = _fk("jobs.id")
    kind: Mapped[str] = mapped_column(sa.String(64))
    name: Mapped[str] = mapped_column(sa.String(512))
    storage_key: Mapped[str] = mapped_column(sa.String(1024))
    size_bytes: Mapped[int | None] = mapped_column(sa.BigInteger)
    sha256: Mapped[str | None] = mapped_column(sa.String(64))
    content_type: Mapped[str | None] = mapped_column(sa.String(255))
    created_at: Mapped[datetime] = _created()

    job: Mapped[Job] = relationship(back_populates="artifacts")


class Webhook(Base):
    __tablename__ = "webhooks"

    id: Mapped[str] = _id()
    tenant_id: Mapped[str] = _fk("tenants.id", index=True)
    url: Mapped[str] = mapped_column(sa.String(2048))
    secret: Mapped[str] = mapped_column(sa.String(255))
    events: Mapped[list[Any]] = mapped_column(default=list)
    active: Mapped[bool] = mapped_column(default=True)
    created_at: Mapped[datetime] = _created()

    tenant: Mapped[Tenant] = relationship(back_populates="webhooks")
    deliveries: Mapped[list[WebhookDelivery]] = _children("webhook")


class WebhookDelivery(Base):
    __tablename__ = "webhook_deliveries"
    __table_args__ = (sa.Index("ix_webhook_deliveries_due", "status", "next_attempt_at"),)

    id: Mapped[str] = _id()
    webhook_id: Mapped[str] = _fk("webhooks.id", index=True)
    job_id: Mapped[str | None] = _fk("jobs.id", nullable=True, index=True)
    event: Mapped[str] = mapped_column(sa.String(64))
    payload: Mapped[dict[str, Any]] = mapped_column(default=dict)
    status: Mapped[DeliveryStatus] = mapped_column(
        _enum(DeliveryStatus, "delivery_status"), default=DeliveryStatus.pending
    )
    attempts: Mapped[int] = mapped_column(default=0)
    next_attempt_at: Mapped[datetime | None]
    last_error: Mapped[str | None] = mapped_column(sa.Text)
    created_at: Mapped[datetime] = _created()

    webhook: Mapped[Webhook] = relationship(back_populates="deliveries")
