"""Projects of the authenticated tenant."""

from __future__ import annotations

import contextlib
import logging
from typing import Annotated

import sqlalchemy as sa
from fastapi import APIRouter, Query, Response, status

from api.deps import DispatcherDep, ProjectDep, SessionDep, StorageDep, TenantDep
from api.schemas import ProjectCreate, ProjectDetail, ProjectOut
from shared.db import crud
from shared.db.models import TERMINAL_JOB_STATUSES, Image, Job, PosRecordRow
from shared.storage import StorageError
from shared.storage.keys import project_prefix

router = APIRouter(prefix="/projects", tags=["projects"])
log = logging.getLogger("midview.api")


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=ProjectOut,
    responses={409: {"description": "The tenant already has a project of that name"}},
)
def create_project(body: ProjectCreate, tenant: TenantDep, session: SessionDep) -> ProjectOut:
    project = crud.create_project(
        session, tenant.id, body.name, description=body.description, crs=body.crs, origin=body.origin
    )
    session.commit()
    return ProjectOut.model_validate(project)


@router.get("", response_model=list[ProjectOut])
def list_projects(
    tenant: TenantDep,
    session: SessionDep,
    name: Annotated[str | None, Query(max_length=200, description="Only the project of this name")] = None,
) -> list[ProjectOut]:
    projects = crud.list_projects(session, tenant.id)
    return [ProjectOut.model_validate(p) for p in projects if name is None or p.name == name]


@router.get("/{project_id}", response_model=ProjectDetail)
def get_project(project: ProjectDep, session: SessionDep) -> ProjectDetail:
    per_set = dict(
        session.execute(
            sa.select(Image.image_set, sa.func.count())
            .where(Image.project_id == project.id)
            .group_by(Image.image_set)
        ).all()
    )
    n_pos = session.scalar(sa.select(sa.func.count()).where(PosRecordRow.project_id == project.id))
    n_jobs = session.scalar(sa.select(sa.func.count()).where(Job.project_id == project.id))
    return ProjectDetail(
        **ProjectOut.model_validate(project).model_dump(),
        images={s: int(per_set.get(s, 0)) for s in ("aerial", "ground")},
        pos_records=int(n_pos or 0),
        jobs=int(n_jobs or 0),
    )


@router.delete("/{project_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_project(
    project: ProjectDep, session: SessionDep, storage: StorageDep, dispatcher: DispatcherDep
) -> Response:
    """Delete the project, its rows (images, POS, jobs, artifacts) and every stored object under it;
    unfinished jobs are revoked first."""
    active = [j.id for j in crud.list_jobs(session, project.id) if j.status not in TERMINAL_JOB_STATUSES]
    prefix = project_prefix(project.tenant_id, project.id)
    uploads = [(u.storage_key, u.storage_upload_id) for u in crud.list_uploads(session, project.id)]
    crud.delete_project(session, project)
    session.commit()
    for job_id in active:
        try:
            dispatcher.revoke(job_id)
        except Exception:
            log.exception("could not revoke job %s of deleted project", job_id)
    try:  # the rows are gone: a storage failure leaves orphan objects, logged, not an error for the client
        for key, storage_upload_id in uploads:
            with contextlib.suppress(StorageError):
                storage.abort_multipart(key, storage_upload_id)
        deleted = storage.delete_prefix(prefix)
        log.info("project %s deleted with %d stored objects", project.id, deleted)
    except (StorageError, OSError):
        log.exception("project %s deleted, but not all of its objects under %s", project.id, prefix)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
