"""Jobs: options, creation, status, progress events, cancel and rerun."""

from __future__ import annotations

import logging

import sqlalchemy as sa
from fastapi import APIRouter, HTTPException, Request, status
from fastapi.responses import StreamingResponse
from sqlalchemy.orm import Session

from api.deps import DispatcherDep, JobDep, ProjectDep, SessionDep, SettingsDep
from api.events import job_events
from api.schemas import JobCreate, JobDetail, JobOut, JobRerun, OptionsOut, OptionSpec, StageRunOut
from shared.db import crud
from shared.db.models import Image, Job, JobStatus, PosRecordRow, Project
from shared.dispatch import Dispatcher
from shared.job_options import JobOptions, option_specs

router = APIRouter(tags=["jobs"])
log = logging.getLogger("midview.api")


def job_out(job: Job) -> JobOut:
    return JobOut(
        id=job.id,
        project_id=job.project_id,
        status=job.status.value,
        current_stage=job.current_stage,
        progress=job.progress,
        progress_percent=round(100.0 * job.progress, 1),
        options=job.options or {},
        timings=job.timings or {},
        metrics=job.metrics or {},
        error=job.error,
        attempt=job.attempt,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
    )


def job_detail(job: Job) -> JobDetail:
    return JobDetail(
        **job_out(job).model_dump(), stages=[StageRunOut.model_validate(r) for r in job.stage_runs]
    )


@router.get("/options", response_model=OptionsOut, summary="Job options with types, defaults and help")
def list_options() -> OptionsOut:
    return OptionsOut(
        options=[OptionSpec(**s) for s in option_specs()], json_schema=JobOptions.model_json_schema()
    )


def _count(session: Session, stmt: sa.Select) -> int:
    return int(session.scalar(stmt) or 0)


def _check_inputs(session: Session, project: Project, options: JobOptions) -> None:
    """409 unless the project has what the selected stages need."""
    n_aerial = _count(
        session,
        sa.select(sa.func.count()).where(Image.project_id == project.id, Image.image_set == "aerial"),
    )
    if n_aerial == 0:
        raise HTTPException(status.HTTP_409_CONFLICT, "the project has no aerial images")
    n_pos = _count(
        session,
        sa.select(sa.func.count())
        .select_from(PosRecordRow)
        .join(
            Image, sa.and_(Image.project_id == PosRecordRow.project_id, Image.name == PosRecordRow.image_name)
        )
        .where(PosRecordRow.project_id == project.id, Image.image_set == "aerial"),
    )
    if n_pos == 0:
        raise HTTPException(status.HTTP_409_CONFLICT, "the project has no POS for its aerial images")
    if options.needs_ground():
        n_ground = _count(
            session,
            sa.select(sa.func.count()).where(Image.project_id == project.id, Image.image_set == "ground"),
        )
        if n_ground == 0:
            raise HTTPException(
                status.HTTP_409_CONFLICT, "the project has no ground images (needed by the selected stages)"
            )


def _submit(session: Session, dispatcher: Dispatcher, job: Job, from_stage: str | None = None) -> None:
    """Hand a committed job to the dispatcher; if that fails, the job fails (503)."""
    try:
        task_id = dispatcher.submit(job.id, from_stage)
    except Exception as e:
        log.exception("dispatch of job %s failed", job.id)
        session.rollback()
        crud.set_job_status(session, job.id, JobStatus.failed, error=f"dispatch failed: {e}")
        session.commit()
        raise HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE, f"job {job.id} could not be queued: {e}"
        ) from e
    if isinstance(task_id, str) and task_id:
        crud.update_job_results(session, job.id, celery_root_id=task_id)
        session.commit()


@router.post(
    "/projects/{project_id}/jobs",
    status_code=status.HTTP_201_CREATED,
    response_model=JobOut,
    responses={
        409: {"description": "The project lacks aerial images, their POS, or ground images"},
        503: {"description": "The job could not be queued"},
    },
)
def create_job(
    project: ProjectDep, session: SessionDep, dispatcher: DispatcherDep, body: JobCreate | None = None
) -> JobOut:
    """Queue a job on the project with the given options (defaults for the rest; no body: all defaults)."""
    options = body.options if body is not None else JobOptions()
    _check_inputs(session, project, options)
    job = crud.create_job(session, project.id, options.model_dump(mode="json"))
    session.commit()
    _submit(session, dispatcher, job)
    log.info("project %s: job %s queued", project.id, job.id)
    return job_out(job)


@router.get("/projects/{project_id}/jobs", response_model=list[JobOut])
def list_jobs(project: ProjectDep, session: SessionDep) -> list[JobOut]:
    return [job_out(j) for j in crud.list_jobs(session, project.id)]


@router.get("/jobs/{job_id}", response_model=JobDetail)
def get_job(job: JobDep) -> JobDetail:
    return job_detail(job)


@router.get(
    "/jobs/{job_id}/events",
    response_class=StreamingResponse,
    responses={
        200: {
            "content": {"text/event-stream": {}},
            "description": "`progress` events (job snapshots), then `end` at a final status",
        }
    },
)
def job_event_stream(
    request: Request, job: JobDep, session: SessionDep, settings: SettingsDep
) -> StreamingResponse:
    """Server-sent events: the job's status, stage and progress whenever they change; ends at a final
    status."""
    session.close()  # the stream polls with its own short sessions; hold no connection meanwhile
    stream = job_events(
        request.app.state.sessionmaker, job.id, settings.events_poll_s, settings.events_heartbeat_s
    )
    headers = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    return StreamingResponse(stream, media_type="text/event-stream", headers=headers)


@router.post(
    "/jobs/{job_id}/cancel",
    response_model=JobOut,
    responses={409: {"description": "The job has already finished"}},
)
def cancel_job(job: JobDep, session: SessionDep, dispatcher: DispatcherDep) -> JobOut:
    """Cancel a queued or running job (idempotent); 409 if it has succeeded or failed."""
    if job.status == JobStatus.cancelled:
        return job_out(job)
    job = crud.set_job_status(session, job.id, JobStatus.cancelled)
    session.commit()
    try:
        dispatcher.revoke(job.id)
    except Exception:  # the row says cancelled: workers stop at their next progress report
        log.exception("revoke of job %s failed", job.id)
    return job_out(job)


@router.post(
    "/jobs/{job_id}/rerun",
    response_model=JobOut,
    responses={409: {"description": "The job has not finished"}, 503: {"description": "Not queued"}},
)
def rerun_job(
    job: JobDep, session: SessionDep, dispatcher: DispatcherDep, body: JobRerun | None = None
) -> JobOut:
    """Run a finished job again (attempt + 1), from from_stage on or from the start."""
    from_stage = body.from_stage if body else None
    if from_stage is not None:
        try:
            JobOptions.model_validate(job.options or {}).stages_from(from_stage)
        except ValueError as e:  # pydantic's ValidationError included
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(e)) from None
    job = crud.rerun_job(session, job.id)  # by id: the row is locked and reloaded
    session.commit()
    _submit(session, dispatcher, job, from_stage)
    return job_out(job)
