"""Campaigns: many surveys submitted as one batch, each a job of its own project; their status (jobs
by state, ground images registered in all) and the rerun of the failed ones from the stage that failed.

The concurrency limit (max_concurrent) is the submitting client's to keep: `midview campaign submit`
starts a survey's job only while fewer than max_concurrent jobs of the campaign are queued or running;
`POST /campaigns/{id}/retry` reruns at most as many failed jobs as there are free slots.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Request, Response, status
from sqlalchemy.orm import Session

from api.auth import Caller
from api.deps import DispatcherDep, SessionDep, TenantDep
from api.routes.jobs import rerun
from api.schemas import (
    CampaignCreate,
    CampaignDetail,
    CampaignJob,
    CampaignOut,
    CampaignRetried,
    CampaignRetry,
)
from shared.db import crud
from shared.db.crud import ConflictError
from shared.db.models import TERMINAL_JOB_STATUSES, Campaign, Job, JobStatus, StageStatus

router = APIRouter(prefix="/campaigns", tags=["campaigns"])


def failed_stage(job: Job) -> str | None:
    """The stage that failed in the job's latest attempt (None if none did)."""
    failed = [r for r in job.stage_runs if r.attempt == job.attempt and r.status == StageStatus.failed]
    return failed[-1].stage if failed else None


def campaign_job(job: Job) -> CampaignJob:
    outcome = (job.metrics or {}).get("outcome") or {}
    return CampaignJob(
        id=job.id,
        project_id=job.project_id,
        project_name=job.project.name,
        key=job.client_key,
        status=job.status.value,
        current_stage=job.current_stage,
        progress_percent=round(100.0 * job.progress, 1),
        attempt=job.attempt,
        failed_stage=failed_stage(job) if job.status == JobStatus.failed else None,
        error=job.error,
        registered=dict(outcome.get("registered") or {}),
        images=dict(outcome.get("images") or {}),
        result=outcome.get("result"),
    )


def campaign_out(campaign: Campaign, jobs: list[Job]) -> CampaignOut:
    by_status: dict[str, int] = {}
    for j in jobs:
        by_status[j.status.value] = by_status.get(j.status.value, 0) + 1
    outcomes = [(j.metrics or {}).get("outcome") or {} for j in jobs if j.status == JobStatus.succeeded]
    return CampaignOut(
        id=campaign.id,
        name=campaign.name,
        max_concurrent=campaign.max_concurrent,
        created_at=campaign.created_at,
        jobs_by_status=by_status,
        active=sum(1 for j in jobs if j.status not in TERMINAL_JOB_STATUSES),
        ground_registered=sum(int((o.get("registered") or {}).get("ground", 0)) for o in outcomes),
        ground_images=sum(int((o.get("images") or {}).get("ground", 0)) for o in outcomes),
        done=all(j.status in TERMINAL_JOB_STATUSES for j in jobs),
    )


def campaign_detail(session: Session, campaign: Campaign) -> CampaignDetail:
    jobs = crud.campaign_jobs(session, campaign.id)
    return CampaignDetail(**campaign_out(campaign, jobs).model_dump(), jobs=[campaign_job(j) for j in jobs])


def get_campaign(campaign_id: str, tenant: TenantDep, session: SessionDep) -> Campaign:
    campaign = crud.get_campaign(session, campaign_id, tenant.id)
    if campaign is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"campaign {campaign_id} not found")
    return campaign


CampaignDep = Annotated[Campaign, Depends(get_campaign)]


def _existing(session: Session, tenant: Caller, body: CampaignCreate) -> Campaign | None:
    campaign = crud.campaign_by_name(session, tenant.id, body.name)
    if campaign is not None and campaign.max_concurrent != body.max_concurrent:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"campaign {body.name!r} exists with max_concurrent {campaign.max_concurrent}",
        )
    return campaign


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=CampaignDetail,
    responses={
        200: {"description": "The tenant's campaign of that name, created before", "model": CampaignDetail},
        409: {"description": "A campaign of that name exists with another max_concurrent"},
    },
)
def create_campaign(
    body: CampaignCreate, tenant: TenantDep, session: SessionDep, response: Response
) -> CampaignDetail:
    """Create a campaign; idempotent by name (a resubmitted manifest finds its campaign)."""
    campaign = _existing(session, tenant, body)
    if campaign is None:
        try:
            campaign = crud.create_campaign(session, tenant.id, body.name, body.max_concurrent)
            session.commit()
        except ConflictError:  # created concurrently
            session.rollback()
            campaign = _existing(session, tenant, body)
            if campaign is None:
                raise
            response.status_code = status.HTTP_200_OK
    else:
        response.status_code = status.HTTP_200_OK
    return campaign_detail(session, campaign)


@router.get("", response_model=list[CampaignOut])
def list_campaigns(tenant: TenantDep, session: SessionDep) -> list[CampaignOut]:
    campaigns = crud.list_campaigns(session, tenant.id)
    return [campaign_out(c, crud.campaign_jobs(session, c.id)) for c in campaigns]


@router.get("/{campaign_id}", response_model=CampaignDetail)
def get_campaign_status(campaign: CampaignDep, session: SessionDep) -> CampaignDetail:
    """Jobs by state, ground images registered in all, and each job with its failed stage."""
    return campaign_detail(session, campaign)


@router.post(
    "/{campaign_id}/retry",
    response_model=CampaignRetried,
    responses={409: {"description": "A failed job's inputs changed since it was created"}},
)
def retry_failed(
    request: Request,
    campaign: CampaignDep,
    session: SessionDep,
    dispatcher: DispatcherDep,
    body: CampaignRetry | None = None,
) -> CampaignRetried:
    """Rerun the campaign's failed jobs, each from the stage that failed (or from the start), as many as
    the free slots allow (or, overriding them, `limit`); the others are listed as waiting."""
    body = body or CampaignRetry()
    jobs = crud.campaign_jobs(session, campaign.id)
    failed = [j for j in jobs if j.status == JobStatus.failed]
    free = max(0, campaign.max_concurrent - sum(1 for j in jobs if j.status not in TERMINAL_JOB_STATUSES))
    n = body.limit if body.limit is not None else free
    rerun_jobs = []
    for job in failed[:n]:
        stage = failed_stage(job) if body.from_failed_stage else None
        rerun_jobs.append(campaign_job(rerun(session, dispatcher, job, stage)))
        request.app.state.status_cache.forget(job.id)  # after the commit: no read caches the old row
    return CampaignRetried(rerun=rerun_jobs, waiting=[j.id for j in failed[n:]])
