"""CRUD helpers. They add and flush; the caller owns the transaction and commits (session_scope, the API
request). Errors: NotFoundError, ConflictError, InvalidTransitionError (all CrudError)."""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import re
import secrets
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

import sqlalchemy as sa
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, joinedload, selectinload, undefer

from shared.config import get_settings
from shared.db.models import (
    IMAGE_SETS,
    TERMINAL_JOB_STATUSES,
    ApiKey,
    Artifact,
    Campaign,
    Image,
    Job,
    JobStatus,
    PosRecordRow,
    Project,
    StageRun,
    StageStatus,
    Tenant,
    Upload,
    utcnow,
)
from shared.db.session import begin_write
from shared.storage.keys import InvalidKeyError, split_image_name

API_KEY_PREFIX = "mv_"
API_KEY_SHOWN = 11  # characters kept in clear as ApiKey.prefix ("mv_" + 8)
SHA256_RE = re.compile(r"^[0-9a-f]{64}$")
T = TypeVar("T")
MAX_PROGRESS_MESSAGE = 500  # characters of a stage's progress message kept (jobs.progress_message)

# allowed job status changes; the same status again is a no-op; leaving a final status needs rerun_job
JOB_TRANSITIONS: dict[JobStatus, frozenset[JobStatus]] = {
    JobStatus.queued: frozenset({JobStatus.running, JobStatus.failed, JobStatus.cancelled}),
    JobStatus.running: frozenset({JobStatus.succeeded, JobStatus.failed, JobStatus.cancelled}),
    JobStatus.succeeded: frozenset(),
    JobStatus.failed: frozenset(),
    JobStatus.cancelled: frozenset(),
}


class CrudError(Exception):
    """Base of the errors of this module."""


class NotFoundError(CrudError, LookupError):
    """The referenced row does not exist (or belongs to another tenant)."""


class ConflictError(CrudError):
    """A unique name is taken, or an image name is reused for a different file."""


class InvalidTransitionError(CrudError):
    """A job or stage status change that the state machine forbids."""


# tenants and API keys
def create_tenant(session: Session, name: str) -> Tenant:
    """A new tenant; ConflictError if the name is taken."""
    if session.scalar(sa.select(Tenant.id).where(Tenant.name == name)) is not None:
        raise ConflictError(f"tenant {name!r} already exists")
    return _add(session, Tenant(name=name), f"tenant {name!r} already exists")


def get_tenant(session: Session, tenant_id: str) -> Tenant | None:
    return session.get(Tenant, str(tenant_id))


def hash_api_key(plaintext: str, pepper: str | None = None) -> str:
    """Hex digest stored for a key: HMAC-SHA256 with the pepper (settings.api_key_pepper), or SHA-256."""
    pepper = get_settings().api_key_pepper if pepper is None else pepper
    if pepper:
        return hmac.new(pepper.encode(), plaintext.encode(), hashlib.sha256).hexdigest()
    return hashlib.sha256(plaintext.encode()).hexdigest()


def create_api_key(
    session: Session, tenant_id: str, name: str = "default", pepper: str | None = None
) -> tuple[ApiKey, str]:
    """A new key of the tenant: (row, plaintext). The plaintext is not stored: show it once."""
    tenant = get_tenant(session, tenant_id)
    if tenant is None:
        raise NotFoundError(f"tenant {tenant_id} not found")
    plaintext = API_KEY_PREFIX + secrets.token_urlsafe(32)
    key = ApiKey(
        tenant_id=tenant.id,
        name=name,
        prefix=plaintext[:API_KEY_SHOWN],
        key_hash=hash_api_key(plaintext, pepper),
    )
    return _add(session, key, "API key collision"), plaintext


def get_api_key(session: Session, plaintext: str, pepper: str | None = None) -> ApiKey | None:
    """The active (not revoked) key row of a plaintext key, or None."""
    if not plaintext or not plaintext.startswith(API_KEY_PREFIX):
        return None
    stmt = sa.select(ApiKey).where(
        ApiKey.key_hash == hash_api_key(plaintext, pepper), ApiKey.revoked_at.is_(None)
    )
    return session.scalar(stmt)


def get_tenant_by_api_key(session: Session, plaintext: str, pepper: str | None = None) -> Tenant | None:
    """The tenant a plaintext key authenticates, or None (unknown or revoked key)."""
    key = get_api_key(session, plaintext, pepper)
    return key.tenant if key is not None else None


def list_api_keys(session: Session, tenant_id: str) -> list[ApiKey]:
    stmt = sa.select(ApiKey).where(ApiKey.tenant_id == str(tenant_id)).order_by(ApiKey.created_at)
    return list(session.scalars(stmt))


def revoke_api_key(session: Session, api_key_id: str, tenant_id: str | None = None) -> ApiKey:
    """Mark a key revoked (idempotent); with tenant_id, only a key of that tenant."""
    key = session.get(ApiKey, str(api_key_id))
    if key is None or (tenant_id is not None and key.tenant_id != str(tenant_id)):
        raise NotFoundError(f"API key {api_key_id} not found")
    if key.revoked_at is None:
        key.revoked_at = utcnow()
        session.flush()
    return key


# projects
def create_project(
    session: Session,
    tenant_id: str,
    name: str,
    description: str | None = None,
    crs: str | None = None,
    origin: tuple[float, float, float] | None = None,
) -> Project:
    """A new project; ConflictError if the tenant already has one of that name."""
    tenant = get_tenant(session, tenant_id)
    if tenant is None:
        raise NotFoundError(f"tenant {tenant_id} not found")
    taken = sa.select(Project.id).where(Project.tenant_id == str(tenant_id), Project.name == name)
    if session.scalar(taken) is not None:
        raise ConflictError(f"project {name!r} already exists")
    lat, lon, h = origin if origin is not None else (None, None, None)
    project = Project(
        tenant_id=tenant.id,
        name=name,
        description=description,
        crs=crs,
        origin_lat=lat,
        origin_lon=lon,
        origin_h=h,
    )
    return _add(session, project, f"project {name!r} already exists")


def get_project(session: Session, project_id: str, tenant_id: str | None = None) -> Project | None:
    """The project, or None if absent or (with tenant_id) owned by another tenant."""
    project = session.get(Project, str(project_id))
    if project is None or (tenant_id is not None and project.tenant_id != str(tenant_id)):
        return None
    return project


def list_projects(session: Session, tenant_id: str) -> list[Project]:
    stmt = sa.select(Project).where(Project.tenant_id == str(tenant_id)).order_by(Project.created_at)
    return list(session.scalars(stmt))


def delete_project(session: Session, project: Project) -> None:
    """Delete a project; the database removes its images, POS, jobs and their children."""
    session.delete(project)
    session.flush()


# images and POS
def image_set_of(name: str) -> str:
    """The set of an image name (`aerial/A0001.jpg` -> `aerial`); ValueError if not aerial/ground."""
    try:
        image_set, _ = split_image_name(name)
    except InvalidKeyError as e:
        raise ValueError(str(e)) from None
    if image_set not in IMAGE_SETS:
        raise ValueError(f"image name {name!r}: the set must be one of {', '.join(IMAGE_SETS)}")
    return image_set


def add_image(
    session: Session,
    project_id: str,
    name: str,
    *,
    sha256: str,
    size_bytes: int,
    storage_key: str,
    width: int | None = None,
    height: int | None = None,
    metadata: dict[str, Any] | None = None,
) -> tuple[Image, bool]:
    """Register an image: (row, created). The same name with the same sha256 returns the existing row
    (created False); the same name with another sha256 raises ConflictError."""
    image_set = image_set_of(name)
    sha256 = sha256.lower()
    if not SHA256_RE.match(sha256):
        raise ValueError(f"sha256 {sha256!r}: expected 64 hex digits")
    project = _project(session, project_id)
    existing = get_image(session, project_id, name)
    if existing is None:
        image = Image(
            project_id=project.id,
            name=name,
            image_set=image_set,
            sha256=sha256,
            size_bytes=size_bytes,
            storage_key=storage_key,
            width=width,
            height=height,
            meta=metadata,
        )
        try:
            with session.begin_nested():
                session.add(image)
            return image, True
        except IntegrityError:  # a concurrent upload of the same name won the race
            existing = get_image(session, project_id, name)
            if existing is None:
                raise
    if existing.sha256 != sha256:
        raise ConflictError(
            f"image {name!r} already exists with another content (sha256 {existing.sha256[:12]}...)"
        )
    return existing, False


def get_image(session: Session, project_id: str, name: str) -> Image | None:
    stmt = sa.select(Image).where(Image.project_id == str(project_id), Image.name == name)
    return session.scalar(stmt)


def list_images(session: Session, project_id: str, image_set: str | None = None) -> list[Image]:
    stmt = sa.select(Image).where(Image.project_id == str(project_id))
    if image_set is not None:
        stmt = stmt.where(Image.image_set == image_set)
    return list(session.scalars(stmt.order_by(Image.name)))


def _field(record: Any, name: str, default: Any = None) -> Any:
    if isinstance(record, Mapping):
        return record.get(name, default)
    return getattr(record, name, default)


def _finite(value: Any, what: str, optional: bool = False) -> float | None:
    if value is None and optional:
        return None
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{what} = {value!r} is not finite")
    return v


def _attitude(R: Any, name: str) -> list[list[float]] | None:
    if R is None:
        return None
    rows = [[float(x) for x in row] for row in R]
    if len(rows) != 3 or any(len(r) != 3 for r in rows):
        raise ValueError(f"POS {name!r}: the attitude must be a 3x3 rotation matrix")
    return rows


def add_pos_records(
    session: Session, project_id: str, records: Iterable[Any], source_format: str | None = None
) -> int:
    """Insert or replace POS rows by image name; records are services.pos.PosRecord objects or mappings
    with the same fields (name, lat, lon, h, R_world_from_cam or attitude, std_xy, std_z, std_att)."""
    project = _project(session, project_id)
    rows = {r.image_name: r for r in list_pos_records(session, project_id)}
    count = 0
    for rec in records:
        name = str(_field(rec, "name"))
        R = _field(rec, "R_world_from_cam", _field(rec, "attitude"))
        values = dict(
            lat=_finite(_field(rec, "lat"), f"{name}: lat"),
            lon=_finite(_field(rec, "lon"), f"{name}: lon"),
            h=_finite(_field(rec, "h"), f"{name}: h"),
            attitude=_attitude(R, name),
            std_xy=_finite(_field(rec, "std_xy"), f"{name}: std_xy", optional=True),
            std_z=_finite(_field(rec, "std_z"), f"{name}: std_z", optional=True),
            std_att=_finite(_field(rec, "std_att"), f"{name}: std_att", optional=True),
            source_format=source_format,
        )
        row = rows.get(name)
        if row is None:
            row = rows[name] = PosRecordRow(project=project, image_name=name)
            session.add(row)
        for k, v in values.items():
            setattr(row, k, v)
        count += 1
    session.flush()
    return count


def list_pos_records(session: Session, project_id: str) -> list[PosRecordRow]:
    stmt = sa.select(PosRecordRow).where(PosRecordRow.project_id == str(project_id))
    return list(session.scalars(stmt.order_by(PosRecordRow.image_name)))


# multipart uploads
def create_upload(
    session: Session,
    project_id: str,
    name: str,
    *,
    storage_key: str,
    storage_upload_id: str,
    size_bytes: int,
    part_size: int,
    part_count: int,
    sha256: str | None = None,
) -> Upload:
    """Register an unfinished multipart upload of an image name; ConflictError when one of that name is
    in progress. The unique (project, name) constraint decides between concurrent starts: the second
    insert waits for the first transaction and then fails."""
    project = _project(session, project_id)
    upload = Upload(
        project_id=project.id,
        name=name,
        storage_key=storage_key,
        storage_upload_id=storage_upload_id,
        size_bytes=size_bytes,
        sha256=sha256.lower() if sha256 else None,
        part_size=part_size,
        part_count=part_count,
    )
    return _add(session, upload, f"an upload of {name!r} is already in progress")


def get_upload(session: Session, project_id: str, upload_id: str) -> Upload | None:
    upload = session.get(Upload, str(upload_id))
    return upload if upload is not None and upload.project_id == str(project_id) else None


def list_uploads(session: Session, project_id: str) -> list[Upload]:
    """The project's unfinished uploads, oldest first."""
    stmt = sa.select(Upload).where(Upload.project_id == str(project_id))
    return list(session.scalars(stmt.order_by(Upload.created_at, Upload.id)))


def uploads_in_progress(session: Session, project_id: str, names: Iterable[str]) -> list[str]:
    """Those of names that an unfinished multipart upload is writing (open or verifying), sorted."""
    wanted = sorted(set(names))
    if not wanted:
        return []
    stmt = sa.select(Upload.name).where(
        Upload.project_id == str(project_id), Upload.name.in_(wanted), Upload.state != "rejected"
    )
    return sorted(session.scalars(stmt))


def drop_rejected_upload(session: Session, project_id: str, name: str) -> None:
    """Delete the rejected upload of name, if any (a new upload of the name replaces it)."""
    session.execute(
        sa.delete(Upload).where(
            Upload.project_id == str(project_id), Upload.name == name, Upload.state == "rejected"
        )
    )


def unfinished_checks(session: Session, project_id: str) -> tuple[list[str], list[tuple[str, str]]]:
    """(names of uploads still being checked, [(name, reason)] of uploads whose check failed)."""
    rows = session.execute(
        sa.select(Upload.name, Upload.state, Upload.error).where(
            Upload.project_id == str(project_id), Upload.state.in_(["verifying", "rejected"])
        )
    ).all()
    verifying = sorted(n for n, st, _ in rows if st == "verifying")
    rejected = sorted((n, e or "") for n, st, e in rows if st == "rejected")
    return verifying, rejected


# jobs
ACTIVE_STATUSES = (JobStatus.queued, JobStatus.running)


def pos_digest(session: Session, project_id: str) -> str:
    """sha256 of the project's POS rows (name, position, attitude, stds), in name order."""
    rows = [
        [r.image_name, r.lat, r.lon, r.h, r.attitude, r.std_xy, r.std_z, r.std_att]
        for r in sorted(list_pos_records(session, project_id), key=lambda r: r.image_name)
    ]
    return hashlib.sha256(json.dumps(rows, separators=(",", ":")).encode()).hexdigest()


def input_snapshot(session: Session, project_id: str) -> dict[str, Any]:
    """What a job is created on: its images (name -> sha256) and the POS rows' digest."""
    images = {im.name: im.sha256 for im in list_images(session, project_id)}
    return {"images": images, "pos_sha256": pos_digest(session, project_id)}


def inputs_changed(session: Session, job: Job, images: list[Image] | None = None) -> list[str]:
    """How the project's inputs differ from the job's snapshot (images gone or replaced, POS changed);
    empty when they are the same (or the job has no snapshot). `images`: the project's, if listed."""
    snap = job.inputs or {}
    if not snap:
        return []
    images = list_images(session, job.project_id) if images is None else images
    now = {im.name: im.sha256 for im in images}
    out = [f"image {n} was deleted" for n in sorted(snap.get("images", {})) if n not in now]
    out += [
        f"image {n} was replaced"
        for n, sha in sorted(snap.get("images", {}).items())
        if now.get(n, sha) != sha
    ]
    if snap.get("pos_sha256") and snap["pos_sha256"] != pos_digest(session, job.project_id):
        out.append("the POS changed")
    return out


def active_jobs(session: Session, project_id: str) -> list[Job]:
    """The project's queued and running jobs."""
    stmt = sa.select(Job).where(Job.project_id == project_id, Job.status.in_(ACTIVE_STATUSES))
    return list(session.scalars(stmt.order_by(Job.created_at)))


def lock_project(session: Session, project_id: str) -> Project:
    """The project, its row locked until the transaction ends (FOR UPDATE on PostgreSQL; SQLite's write
    transactions are serial already): what changes a project's inputs and what snapshots them for a job
    take it first, so that one waits for the other (a delete never removes an image that a job created
    meanwhile has frozen). NotFoundError when absent."""
    project = session.get(Project, str(project_id), with_for_update=True, populate_existing=True)
    if project is None:
        raise NotFoundError(f"project {project_id} not found")
    return project


def check_inputs_free(session: Session, project_id: str, image_name: str | None = None) -> None:
    """ConflictError when a queued or running job uses the image (or, without a name, any input); the
    project's row stays locked until the caller's transaction ends (lock_project)."""
    lock_project(session, project_id)
    busy = [
        j.id
        for j in active_jobs(session, project_id)
        if image_name is None or image_name in (j.inputs or {}).get("images", {image_name: None})
    ]
    if busy:
        what = f"image {image_name}" if image_name else "the project's inputs"
        raise ConflictError(
            f"{what} in use by job(s) {', '.join(busy)} (queued or running): try when they end"
        )


def create_job(
    session: Session,
    project_id: str,
    options: dict[str, Any] | None = None,
    inputs: dict[str, Any] | None = None,
    client_key: str | None = None,
    campaign_id: str | None = None,
) -> Job:
    """A queued job of the project, on a snapshot of its inputs (input_snapshot, by default now's);
    ConflictError if the project has a job with this client_key already (job_by_key finds it)."""
    project = lock_project(session, project_id)  # the snapshot waits for a delete of its inputs under way
    snap = input_snapshot(session, project.id) if inputs is None else inputs
    job = Job(
        project_id=project.id,
        options=dict(options or {}),
        inputs=snap,
        client_key=client_key,
        campaign_id=campaign_id,
    )
    return _add(session, job, f"job key {client_key!r} exists" if client_key else "job exists")


def job_by_key(session: Session, project_id: str, client_key: str) -> Job | None:
    stmt = sa.select(Job).where(Job.project_id == str(project_id), Job.client_key == client_key)
    return session.scalar(stmt)


def get_job(
    session: Session, job_id: str, tenant_id: str | None = None, with_stages: bool = False
) -> Job | None:
    """The job, or None if absent or (with tenant_id) in a project of another tenant; its project loaded
    with it, and with_stages its stage runs (two queries in all: what a status read needs)."""
    stmt = sa.select(Job).options(joinedload(Job.project)).where(Job.id == str(job_id))
    if with_stages:
        stmt = stmt.options(selectinload(Job.stage_runs))
    job = session.scalar(stmt)
    if job is None or (tenant_id is not None and job.project.tenant_id != str(tenant_id)):
        return None
    return job


def job_status_rows(session: Session, job_id: str) -> tuple[str, sa.Row, list[sa.Row]] | None:
    """(the job's tenant id, the job's row, its stage runs' rows in start order), or None: the columns as
    plain rows, without the ORM's identity map and loaders (a status read clients poll is this and
    nothing more: two light queries). The caller checks the tenant."""
    jobs, runs = Job.__table__, StageRun.__table__
    stmt = (
        sa.select(Project.tenant_id, *jobs.c)
        .join(Project.__table__, Project.id == jobs.c.project_id)
        .where(jobs.c.id == str(job_id))
    )
    job = session.execute(stmt).first()
    if job is None:
        return None
    columns = [c for c in runs.c if c.name != "log"]  # the logs are read apart (stage_logs)
    stage_rows = session.execute(
        sa.select(*columns).where(runs.c.job_id == job.id).order_by(runs.c.started_at)
    ).all()
    return job.tenant_id, job, list(stage_rows)


def list_jobs(session: Session, project_id: str) -> list[Job]:
    stmt = sa.select(Job).where(Job.project_id == str(project_id)).order_by(Job.created_at)
    return list(session.scalars(stmt))


def _project(session: Session, project_id: str) -> Project:
    project = session.get(Project, str(project_id))
    if project is None:
        raise NotFoundError(f"project {project_id} not found")
    return project


def _job(session: Session, job: Job | str) -> Job:
    """A Job as given, or loaded by id with its row locked (FOR UPDATE on PostgreSQL)."""
    if isinstance(job, Job):
        return job
    begin_write(session)  # SQLite: take the write lock before reading what will be written
    found = session.get(Job, str(job), with_for_update=True, populate_existing=True)
    if found is None:
        raise NotFoundError(f"job {job} not found")
    return found


def set_job_status(
    session: Session, job: Job | str, status: JobStatus | str, error: str | None = None
) -> Job:
    """Move a job to status (JOB_TRANSITIONS); stamps started_at/finished_at; InvalidTransitionError."""
    job = _job(session, job)
    new = JobStatus(status)
    if new != job.status and new not in JOB_TRANSITIONS[job.status]:
        raise InvalidTransitionError(f"job {job.id}: {job.status.value} -> {new.value} is not allowed")
    if new == job.status:
        return job
    now = utcnow()
    job.status = new
    if new == JobStatus.running and job.started_at is None:
        job.started_at = now
    if new in TERMINAL_JOB_STATUSES:
        job.finished_at = now
    if new == JobStatus.succeeded:
        job.progress = 1.0
    if error is not None:
        job.error = error
    session.flush()
    return job


def update_job_progress(
    session: Session, job: Job | str, progress: float, stage: str | None = None, message: str | None = None
) -> Job:
    """Report progress in [0, 1] (and the current stage, and what it is doing) of a live job; a queued job
    becomes running. InvalidTransitionError if the job has finished (e.g. was cancelled): the worker
    should stop."""
    job = _job(session, job)
    if not 0.0 <= float(progress) <= 1.0:
        raise ValueError(f"progress {progress} outside [0, 1]")
    if job.status in TERMINAL_JOB_STATUSES:
        raise InvalidTransitionError(f"job {job.id} is {job.status.value}")
    if job.status == JobStatus.queued:
        set_job_status(session, job, JobStatus.running)
    job.progress = float(progress)
    if stage is not None:
        job.current_stage = stage
    if message is not None:
        job.progress_message = message[:MAX_PROGRESS_MESSAGE]
    session.flush()
    return job


def update_job_results(
    session: Session, job: Job | str, metrics: dict[str, Any] | None = None, celery_root_id: str | None = None
) -> Job:
    """Merge metrics into the job and/or record the Celery root task id."""
    job = _job(session, job)
    if metrics:
        job.metrics = {**(job.metrics or {}), **metrics}
    if celery_root_id is not None:
        job.celery_root_id = celery_root_id
    session.flush()
    return job


def rerun_job(session: Session, job: Job | str, force_from: str | None = None) -> Job:
    """Reset a finished job to queued for another attempt (attempt + 1); its stage runs stay as history.
    force_from: the attempt runs the stages from this one on again even where they are up to date."""
    job = _job(session, job)
    if job.status not in TERMINAL_JOB_STATUSES:
        raise InvalidTransitionError(f"job {job.id} is {job.status.value}; only a finished job can rerun")
    job.status = JobStatus.queued
    job.attempt += 1
    job.progress = 0.0
    job.current_stage = job.progress_message = None
    job.error = None
    job.started_at = job.finished_at = None
    job.celery_root_id = None
    job.force_from = force_from
    job.timings, job.metrics = {}, {}
    session.flush()
    return job


# campaigns
def create_campaign(session: Session, tenant_id: str, name: str, max_concurrent: int = 2) -> Campaign:
    """A new campaign; ConflictError if the tenant has one of that name (campaign_by_name finds it)."""
    campaign = Campaign(tenant_id=str(tenant_id), name=name, max_concurrent=max_concurrent)
    return _add(session, campaign, f"campaign {name!r} already exists")


def get_campaign(session: Session, campaign_id: str, tenant_id: str | None = None) -> Campaign | None:
    """The campaign, or None if absent or (with tenant_id) another tenant's."""
    campaign = session.get(Campaign, str(campaign_id))
    if campaign is None or (tenant_id is not None and campaign.tenant_id != str(tenant_id)):
        return None
    return campaign


def campaign_by_name(session: Session, tenant_id: str, name: str) -> Campaign | None:
    stmt = sa.select(Campaign).where(Campaign.tenant_id == str(tenant_id), Campaign.name == name)
    return session.scalar(stmt)


def list_campaigns(session: Session, tenant_id: str) -> list[Campaign]:
    stmt = sa.select(Campaign).where(Campaign.tenant_id == str(tenant_id)).order_by(Campaign.created_at)
    return list(session.scalars(stmt))


def campaign_jobs(session: Session, campaign_id: str) -> list[Job]:
    stmt = sa.select(Job).where(Job.campaign_id == str(campaign_id)).order_by(Job.created_at)
    return list(session.scalars(stmt))


# stages and artifacts
def start_stage(session: Session, job: Job | str, stage: str, worker: str | None = None) -> StageRun:
    """Record the start of a stage (the job becomes running, current_stage = stage)."""
    job = _job(session, job)
    if job.status in TERMINAL_JOB_STATUSES:
        raise InvalidTransitionError(f"job {job.id} is {job.status.value}; cannot start stage {stage!r}")
    if job.status == JobStatus.queued:
        set_job_status(session, job, JobStatus.running)
    previous = session.scalar(
        sa.select(sa.func.count())
        .select_from(StageRun)
        .where(StageRun.job_id == job.id, StageRun.stage == stage)
    )
    run = StageRun(job=job, stage=stage, attempt=int(previous or 0) + 1, worker=worker)
    session.add(run)
    job.current_stage = stage
    session.flush()
    return run


def finish_stage(
    session: Session,
    run: StageRun,
    status: StageStatus | str = StageStatus.succeeded,
    error: str | None = None,
    output_key: str | None = None,
) -> StageRun:
    """Close a running stage run; its duration goes into job.timings[stage] (seconds)."""
    new = StageStatus(status)
    if new == StageStatus.running:
        raise InvalidTransitionError("finish_stage needs a final status")
    if run.status != StageStatus.running:
        raise InvalidTransitionError(f"stage run {run.stage!r} is already {run.status.value}")
    now = utcnow()
    run.status, run.error, run.output_key = new, error, output_key
    run.finished_at = now
    run.duration_s = (now - run.started_at).total_seconds()
    job = run.job
    job.timings = {**(job.timings or {}), run.stage: run.duration_s}
    session.flush()
    return run


def append_stage_log(session: Session, run_id: str, text: str) -> None:
    """Append lines to a stage run's log in one statement (the units of a fan-out stage append to the
    same run from several processes; no read-modify-write)."""
    session.execute(
        sa.update(StageRun)
        .where(StageRun.id == run_id)
        .values(log=sa.func.coalesce(StageRun.log, "") + text)
        .execution_options(synchronize_session=False)
    )


def stage_logs(session: Session, job_id: str) -> list[tuple[StageRun, str]]:
    """(stage run, its log) of a job's stage runs in start order, the runs without a log too."""
    runs = session.scalars(
        sa.select(StageRun)
        .where(StageRun.job_id == str(job_id))
        .order_by(StageRun.started_at)
        .options(undefer(StageRun.log))
    ).all()
    return [(r, r.log or "") for r in runs]


def record_artifact(
    session: Session,
    job: Job | str,
    kind: str,
    name: str,
    storage_key: str,
    size_bytes: int | None = None,
    sha256: str | None = None,
    content_type: str | None = None,
) -> Artifact:
    """Insert or replace (by name) an artifact of the job."""
    job = _job(session, job)
    artifact = session.scalar(sa.select(Artifact).where(Artifact.job_id == job.id, Artifact.name == name))
    if artifact is None:
        artifact = Artifact(job=job, name=name)
        session.add(artifact)
    artifact.kind, artifact.storage_key = kind, storage_key
    artifact.size_bytes, artifact.sha256, artifact.content_type = size_bytes, sha256, content_type
    artifact.created_at = utcnow()
    session.flush()
    return artifact


def list_artifacts(session: Session, job_id: str) -> list[Artifact]:
    stmt = sa.select(Artifact).where(Artifact.job_id == str(job_id)).order_by(Artifact.name)
    return list(session.scalars(stmt))


def _add(session: Session, obj: T, conflict: str) -> T:
    """Add and flush obj in a savepoint; a unique violation becomes ConflictError(conflict)."""
    try:
        with session.begin_nested():
            session.add(obj)
    except IntegrityError as e:
        raise ConflictError(conflict) from e
    return obj
