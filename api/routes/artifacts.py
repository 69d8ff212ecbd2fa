"""Job outputs: artifact listing and download, and the aerial-ground pairs of a job's match file."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import sqlalchemy as sa
from fastapi import APIRouter, HTTPException, Query, Request, status
from fastapi import Path as FastApiPath
from fastapi.responses import StreamingResponse
from sqlalchemy.orm import Session

from api.bundles import BUNDLES, members, stream_zip
from api.deps import JobDep, SessionDep, SettingsDep, StorageDep, TenantDep
from api.downloads import content_disposition, stream_object
from api.matches import MATCH_KINDS, list_pairs, local_copy, read_pair
from api.schemas import ArtifactOut, PairList, PairMatchesOut, PairSummary
from shared.db import crud
from shared.db.models import Artifact, Job
from shared.storage import Storage, StorageError

router = APIRouter(tags=["artifacts"])


def _download_url(request: Request, storage: Storage, artifact: Artifact) -> str:
    """A presigned URL when the storage has real ones (S3), else the API's download route."""
    try:
        url = storage.presigned_get_url(artifact.storage_key)
    except StorageError:
        url = None
    if url and url.startswith(("http://", "https://")):
        return url
    return str(request.url_for("download_artifact", artifact_id=artifact.id))


def _artifact_out(request: Request, storage: Storage, artifact: Artifact) -> ArtifactOut:
    out = ArtifactOut.model_validate(artifact)
    out.download_url = _download_url(request, storage, artifact)
    return out


def _artifact(session: Session, tenant_id: str, artifact_id: str) -> Artifact:
    """The tenant's artifact; 404 when absent or another tenant's."""
    artifact = session.get(Artifact, artifact_id)
    if artifact is None or artifact.job.project.tenant_id != tenant_id:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"artifact {artifact_id} not found")
    return artifact


@router.get("/jobs/{job_id}/artifacts", response_model=list[ArtifactOut])
def list_artifacts(
    request: Request, job: JobDep, session: SessionDep, storage: StorageDep
) -> list[ArtifactOut]:
    return [_artifact_out(request, storage, a) for a in crud.list_artifacts(session, job.id)]


@router.get("/artifacts/{artifact_id}", response_model=ArtifactOut)
def get_artifact(
    request: Request, artifact_id: str, tenant: TenantDep, session: SessionDep, storage: StorageDep
) -> ArtifactOut:
    return _artifact_out(request, storage, _artifact(session, tenant.id, artifact_id))


@router.get("/artifacts/{artifact_id}/download", response_class=StreamingResponse)
def download_artifact(
    artifact_id: str, tenant: TenantDep, session: SessionDep, storage: StorageDep
) -> StreamingResponse:
    """The artifact's bytes, streamed from storage."""
    artifact = _artifact(session, tenant.id, artifact_id)
    filename = artifact.name.rsplit("/", 1)[-1]
    session.close()  # hold no database connection while the bytes flow
    return stream_object(storage, artifact.storage_key, filename, artifact.content_type)


@router.get(
    "/jobs/{job_id}/bundles/{bundle}.zip",
    response_class=StreamingResponse,
    responses={
        200: {"content": {"application/zip": {}}},
        404: {"description": "No such bundle, or nothing in it yet"},
    },
)
def download_bundle(
    job: JobDep,
    session: SessionDep,
    storage: StorageDep,
    bundle: Annotated[str, FastApiPath(description=f"One of: {', '.join(BUNDLES)}")],
) -> StreamingResponse:
    """The job's results as one zip: `gis` (GeoPackage, GeoJSON, OPK, LAS of the combined model, and its
    report) or `colmap` (the combined model, its georeference and report)."""
    spec = BUNDLES.get(bundle)
    if spec is None:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"no bundle {bundle!r}: bundles are {', '.join(BUNDLES)}"
        )
    files = [(a.name, a.storage_key) for a in members(spec, crud.list_artifacts(session, job.id))]
    if not files:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"job {job.id} has nothing for the {bundle} bundle yet"
        )
    filename = f"midview-{job.id[:8]}-{bundle}.zip"
    session.close()  # hold no database connection while the bytes flow
    headers = {"Content-Disposition": content_disposition(filename)}
    return StreamingResponse(stream_zip(storage, files), media_type="application/zip", headers=headers)


def _match_artifact(session: Session, job: Job, name: str | None) -> Artifact:
    """The named artifact, or the job's newest match file."""
    stmt = sa.select(Artifact).where(Artifact.job_id == job.id)
    stmt = stmt.where(Artifact.name == name) if name else stmt.where(Artifact.kind.in_(MATCH_KINDS))
    artifact = session.scalars(stmt.order_by(Artifact.created_at.desc())).first()
    if artifact is None:
        what = f"artifact {name!r}" if name else "match file"
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job.id} has no {what}")
    return artifact


def _cache_dir(settings: SettingsDep) -> Path:
    return Path(settings.cache_dir) if settings.cache_dir else settings.data_dir / "cache"


def _open_match_file(storage: Storage, artifact: Artifact, cache: Path) -> Path:
    try:
        return local_copy(storage, artifact, cache)
    except OSError as e:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"{artifact.name}: unreadable: {e}") from e


ArtifactName = Annotated[str | None, Query(description="Artifact name; default: the newest match file")]


@router.get("/jobs/{job_id}/pairs", response_model=PairList)
def job_pairs(
    job: JobDep,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    artifact: ArtifactName = None,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
    offset: Annotated[int, Query(ge=0)] = 0,
) -> PairList:
    """Aerial-ground pairs of the job's match file with their match counts (aerial first)."""
    art = _match_artifact(session, job, artifact)
    path = _open_match_file(storage, art, _cache_dir(settings))
    try:
        method, pairs = list_pairs(path)
    except (OSError, ValueError, KeyError) as e:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, f"{art.name}: not a match file: {e}"
        ) from e
    return PairList(
        artifact=art.name,
        method=method,
        total=len(pairs),
        pairs=[PairSummary(**p) for p in pairs[offset : offset + limit]],
    )


@router.get("/jobs/{job_id}/pairs/aerial/{aerial_file}/ground/{ground_file}", response_model=PairMatchesOut)
def job_pair(
    job: JobDep,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    aerial_file: str,
    ground_file: str,
    artifact: ArtifactName = None,
    inliers_only: Annotated[bool, Query(description="Only the matcher's verified matches")] = False,
) -> PairMatchesOut:
    """One pair's matches: matched keypoint coordinates in both images (COLMAP pixel convention)."""
    art = _match_artifact(session, job, artifact)
    path = _open_match_file(storage, art, _cache_dir(settings))
    aerial, ground = f"aerial/{aerial_file}", f"ground/{ground_file}"
    try:
        pair = read_pair(path, aerial, ground, inliers_only)
    except (OSError, ValueError) as e:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, f"{art.name}: not a match file: {e}"
        ) from e
    except KeyError:
        pair = None
    if pair is None:
        raise HTTPException(
            status.HTTP_404_NOT_FOUND, f"no matches between {aerial} and {ground} in {art.name}"
        )
    return PairMatchesOut(artifact=art.name, **pair)
