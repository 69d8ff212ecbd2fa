"""Jobs: options, creation, status, progress events, cancel and rerun."""

from __future__ import annotations

import json
import logging
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Query, Request, Response, status
from fastapi.responses import PlainTextResponse, StreamingResponse
from sqlalchemy.orm import Session, sessionmaker

from api.deps import (
    DispatcherDep,
    JobDep,
    ProjectDep,
    SessionDep,
    SettingsDep,
    StorageDep,
    TenantDep,
    run_db,
)
from api.events import job_events
from api.schemas import (
    EstimateOut,
    JobCreate,
    JobDetail,
    JobOut,
    JobRerun,
    OptionsOut,
    OptionSpec,
    ProfileOut,
    StageRunOut,
)
from api.status_cache import Entry
from services.pipeline import PROFILE_HELP, PROFILES, JobOptions, costs, option_specs
from shared.db import crud
from shared.db.crud import ConflictError
from shared.db.models import Job, JobStatus, Project
from shared.dispatch import Dispatcher, offered_profile
from shared.storage import Storage, StorageKeyError
from shared.storage.keys import cameras_key

router = APIRouter(tags=["jobs"])
log = logging.getLogger("midview.api")


def job_fields(job: Any) -> dict[str, Any]:
    """JobOut's fields of a job (an ORM Job, or a row with the jobs table's columns)."""
    metrics = job.metrics or {}
    return dict(
        id=job.id,
        project_id=job.project_id,
        status=job.status.value,
        current_stage=job.current_stage,
        progress=job.progress,
        progress_percent=round(100.0 * job.progress, 1),
        progress_message=getattr(job, "progress_message", None),
        options=job.options or {},
        timings=job.timings or {},
        metrics=metrics,
        outcome=metrics.get("outcome"),
        error=job.error,
        attempt=job.attempt,
        force_from=getattr(job, "force_from", None),
        key=job.client_key,
        campaign_id=job.campaign_id,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
    )


def job_out(job: Job) -> JobOut:
    return JobOut(**job_fields(job))


def job_detail(job: Any, stage_runs: list[Any] | None = None) -> JobDetail:
    runs = job.stage_runs if stage_runs is None else stage_runs
    return JobDetail(**job_fields(job), stages=[StageRunOut.model_validate(r) for r in runs])


@router.get("/options", response_model=OptionsOut, summary="Job options with types, defaults and help")
def list_options(
    dispatcher: DispatcherDep,
    aerial: Annotated[int | None, Query(ge=0, le=1_000_000, description="Aerial images of a survey")] = None,
    ground: Annotated[int | None, Query(ge=0, le=1_000_000, description="Ground images of a survey")] = None,
) -> OptionsOut:
    """The profiles (whose defaults a job takes; `offered`: the one a job that names none gets here) and
    every option with its type, default per profile and help; with `aerial` and `ground`, each profile's
    estimated seconds per stage for a survey of that size (services.pipeline.costs)."""
    offered = offered_profile(dispatcher)
    profiles = []
    for name, values in PROFILES.items():
        estimate = None
        if aerial is not None and ground is not None:
            options = JobOptions.model_validate({"profile": name})
            estimate = EstimateOut(aerial=aerial, ground=ground, **costs.estimate(options, aerial, ground))
        profiles.append(
            ProfileOut(
                name=name, help=PROFILE_HELP[name], options=values, offered=name == offered, estimate=estimate
            )
        )
    return OptionsOut(
        profiles=profiles,
        options=[OptionSpec(**s) for s in option_specs()],
        json_schema=JobOptions.model_json_schema(),
    )


MIN_AERIAL = 3  # georeferencing fits a similarity to at least three camera centres


def _names(items: list[str], limit: int = 10) -> str:
    return ", ".join(items[:limit]) + (f" and {len(items) - limit} more" if len(items) > limit else "")


def _check_inputs(session: Session, storage: Storage, project: Project, options: JobOptions) -> None:
    """409 unless the project has what the selected stages need: at least MIN_AERIAL aerial images,
    ground images where the stages need them, a POS row for every image, and intrinsics for each set
    (its cameras.json entry, else the EXIF focal length of every image of the set); and none of its
    uploads still being checked (with Retry-After) or rejected by the check."""
    verifying, rejected = crud.unfinished_checks(session, project.id)
    if verifying:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"{len(verifying)} uploaded image(s) are still being checked ({_names(verifying)}): retry "
            "in a few seconds",
            headers={"Retry-After": "2"},
        )
    if rejected:
        reasons = [f"{n}: {why}" for n, why in rejected]
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"{len(rejected)} uploaded image(s) failed their check ({'; '.join(reasons[:5])}): upload them "
            "again or delete those uploads",
        )
    sets = ["aerial", "ground"] if options.needs_ground() else ["aerial"]
    images = {s: crud.list_images(session, project.id, s) for s in sets}
    if not images["aerial"]:
        raise HTTPException(status.HTTP_409_CONFLICT, "the project has no aerial images")
    if len(images["aerial"]) < MIN_AERIAL:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"the project has {len(images['aerial'])} aerial image(s): the aerial SfM and its georeference "
            f"need at least {MIN_AERIAL}",
        )
    if "ground" in images and not images["ground"]:
        raise HTTPException(
            status.HTTP_409_CONFLICT, "the project has no ground images (needed by the selected stages)"
        )
    with_pos = {r.image_name for r in crud.list_pos_records(session, project.id)}
    if not any(im.name in with_pos for im in images["aerial"]):
        raise HTTPException(status.HTTP_409_CONFLICT, "the project has no POS for its aerial images")
    missing = [im.name for s in sets for im in images[s] if im.name not in with_pos]
    if missing:
        raise HTTPException(
            status.HTTP_409_CONFLICT, f"{len(missing)} image(s) have no POS row: {_names(missing)}"
        )
    try:
        cameras = json.loads(storage.get_bytes(cameras_key(project.tenant_id, project.id)))
    except StorageKeyError:
        cameras = {}
    for s in sets:
        if s in cameras:
            continue
        no_focal = [
            im.name
            for im in images[s]
            if "exif_focal_px" in (im.meta or {}) and not (im.meta or {})["exif_focal_px"]
        ]
        if no_focal:
            raise HTTPException(
                status.HTTP_409_CONFLICT,
                f"no intrinsics for the {s} images: the project's cameras.json has no {s!r} entry and "
                f"{len(no_focal)} of them have no EXIF focal length ({_names(no_focal)}); "
                f"PUT /projects/{project.id}/cameras",
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


def _same_job(existing: Job, options: dict, campaign_id: str | None) -> Job:
    """The job a repeated creation with its key asks for; 409 when that asks for something else."""
    if existing.options != options or existing.campaign_id != campaign_id:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"job key {existing.client_key!r} is taken by job {existing.id} with other options or campaign",
        )
    return existing


@router.post(
    "/projects/{project_id}/jobs",
    status_code=status.HTTP_201_CREATED,
    response_model=JobOut,
    responses={
        200: {"description": "A job with this key exists already: that job", "model": JobOut},
        404: {"description": "No such campaign"},
        409: {
            "description": "The project lacks aerial images, ground images, POS rows or intrinsics; or the "
            "key is taken by a job with other options"
        },
        503: {"description": "The job could not be queued"},
    },
)
def create_job(
    project: ProjectDep,
    session: SessionDep,
    dispatcher: DispatcherDep,
    storage: StorageDep,
    response: Response,
    body: JobCreate | None = None,
) -> JobOut:
    """Queue a job on the project with the given options (defaults for the rest; no body: all defaults),
    on a snapshot of its inputs (images and POS: deleting or replacing them while it runs is 409).
    With a `key`, the creation is idempotent: repeating it returns the job made the first time."""
    body = body if body is not None else JobCreate()
    options = body.options
    if "profile" not in options.model_fields_set:  # the profile this service's workers run
        offered = offered_profile(dispatcher)
        if offered != options.profile:
            options = options.with_profile(offered)
    if options.out_crs is None and project.crs:  # the project's output CRS, unless the job names one
        options = options.model_copy(update={"out_crs": project.crs})
    dumped = options.model_dump(mode="json")
    if body.key is not None and (existing := crud.job_by_key(session, project.id, body.key)) is not None:
        response.status_code = status.HTTP_200_OK
        return job_out(_same_job(existing, dumped, body.campaign_id))
    campaign_id = body.campaign_id
    if campaign_id is not None and crud.get_campaign(session, campaign_id, project.tenant_id) is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"campaign {body.campaign_id} not found")
    _check_inputs(session, storage, project, options)
    try:
        job = crud.create_job(session, project.id, dumped, client_key=body.key, campaign_id=body.campaign_id)
        session.commit()
    except ConflictError:  # a concurrent creation with the same key won: answer with its job
        session.rollback()
        existing = crud.job_by_key(session, project.id, body.key or "")
        if existing is None:
            raise
        response.status_code = status.HTTP_200_OK
        return job_out(_same_job(existing, dumped, body.campaign_id))
    _submit(session, dispatcher, job)
    log.info("project %s: job %s queued", project.id, job.id)
    return job_out(job)


@router.get("/projects/{project_id}/jobs", response_model=list[JobOut])
def list_jobs(
    project: ProjectDep,
    session: SessionDep,
    key: Annotated[str | None, Query(max_length=128, description="Only the job with this key")] = None,
) -> list[JobOut]:
    if key is not None:
        job = crud.job_by_key(session, project.id, key)
        return [job_out(job)] if job is not None else []
    return [job_out(j) for j in crud.list_jobs(session, project.id)]


def read_job_entry(maker: sessionmaker[Session], job_id: str) -> Entry | None:
    """The job as GET /jobs/{id} answers it, with its tenant, read in a session of its own (closed on
    return); None when there is no such job."""
    with maker() as session:
        rows = crud.job_status_rows(session, job_id)
    if rows is None:
        return None
    tenant_id, job, stage_runs = rows
    return Entry(tenant_id, job_detail(job, stage_runs).model_dump_json().encode())


@router.get("/jobs/{job_id}", response_model=JobDetail)
async def get_job(
    request: Request, job_id: Annotated[str, Path(description="Job id")], tenant: TenantDep
) -> Response:
    """The job, its stages and outcome: the status read clients poll. Served from the app's StatusCache
    (api.status_cache: what workers wrote shows within status_cache_s); a miss reads the database in one
    trip to a worker thread, with a session of its own."""
    state = request.app.state

    async def load() -> Entry | None:
        return await run_db(request, read_job_entry, state.sessionmaker, job_id)

    entry = await state.status_cache.get(job_id, tenant.id, load)
    if entry is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} not found")
    return Response(entry.body, media_type="application/json")


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
    cache, job_id = request.app.state.status_cache, job.id
    stream = job_events(
        request.app.state.job_watch,
        job_id,
        settings.events_heartbeat_s,
        on_change=lambda: cache.forget(job_id),
    )
    headers = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    return StreamingResponse(stream, media_type="text/event-stream", headers=headers)


@router.get(
    "/jobs/{job_id}/log",
    response_class=PlainTextResponse,
    responses={200: {"content": {"text/plain": {}}, "description": "The job's log, stage run by stage run"}},
)
def job_log(job: JobDep, session: SessionDep) -> PlainTextResponse:
    """The job's log as its workers kept it: for each stage run (every attempt, in start order) a heading
    line, then what the stage logged while it ran (its progress and its steps' messages)."""
    parts = []
    for run, text in crud.stage_logs(session, job.id):
        took = f", {run.duration_s:.1f} s" if run.duration_s is not None else ""
        head = f"== {run.stage} (attempt {run.attempt}, {run.status.value}{took}"
        head += f", {run.worker})" if run.worker else ")"
        parts.append(head + "\n" + text + (f"error: {run.error}\n" if run.error else ""))
    return PlainTextResponse("".join(parts), headers={"Cache-Control": "no-cache"})


@router.post(
    "/jobs/{job_id}/cancel",
    response_model=JobOut,
    responses={409: {"description": "The job has already finished"}},
)
def cancel_job(request: Request, job: JobDep, session: SessionDep, dispatcher: DispatcherDep) -> JobOut:
    """Cancel a queued or running job (idempotent); 409 if it has succeeded or failed."""
    if job.status == JobStatus.cancelled:
        return job_out(job)
    job = crud.set_job_status(session, job.id, JobStatus.cancelled)
    session.commit()
    request.app.state.status_cache.forget(job.id)
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
    request: Request,
    job: JobDep,
    session: SessionDep,
    dispatcher: DispatcherDep,
    body: JobRerun | None = None,
) -> JobOut:
    """Run a finished job again (attempt + 1), from from_stage on or from the start; stages that are up
    to date are skipped unless `force`."""
    try:
        return job_out(
            rerun(session, dispatcher, job, body.from_stage if body else None, bool(body and body.force))
        )
    finally:
        request.app.state.status_cache.forget(job.id)


def rerun(
    session: Session, dispatcher: Dispatcher, job: Job, from_stage: str | None, force: bool = False
) -> Job:
    """Queue a finished job again from from_stage (None: from the start), with `force` running those
    stages even where they are up to date; 422 for a stage the job does not run, 409 when its inputs
    changed, 503 when it cannot be queued."""
    stages: list[str] = []
    if from_stage is not None or force:
        try:
            stages = JobOptions.model_validate(job.options or {}).stages_from(from_stage)
        except ValueError as e:  # pydantic's ValidationError included
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(e)) from None
    changed = crud.inputs_changed(session, job)
    if changed:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"the job's inputs changed since it was created ({'; '.join(changed[:10])}): create a new job",
        )
    job = crud.rerun_job(session, job.id, stages[0] if force and stages else None)  # by id: locked, reloaded
    session.commit()
    _submit(session, dispatcher, job, from_stage)
    return job
